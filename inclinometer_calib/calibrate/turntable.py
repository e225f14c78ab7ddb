"""The patent's magnetometer calibration on a non-magnetic turntable (second seed document) — ROS-free.

Model (the seed's eq. 5, completed).  Each real sensor axis is a unit vector ``u_i`` in the frame
of the axes marked on the housing (the tool frame), tilted from its marked axis by ``α_i``, its
projection on the plane of the other two marked axes at ``β_i`` (cyclically: x_m's projection on
yz from y towards z, y_m's on zx from z towards x, z_m's on xy from x towards y)::

    u_x = (cos α1, sin α1·cos β1, sin α1·sin β1)
    u_y = (sin α2·sin β2, cos α2, sin α2·cos β2)
    u_z = (sin α3·cos β3, sin α3·sin β3, cos α3)

    o_i = k_i·(u_i · B) + B_i0           i.e.  o = M·B + b,  M = diag(k)·U  (rows k_i·u_i)

``M`` is the paper's ``K·E`` written another way: ``K_i = k_i·cos α_i`` and ``e`` = the rows of
``U`` over their diagonal, so a turntable calibration is a record of the project's base model
(:meth:`errormodel.TriadModel.from_matrix`), and the correction path is the one every record uses.

Procedure.  In a uniform field the probe is mounted with two marked axes in the table plane
(mount ``xy``: marked x and y in the plane, the table turning about marked z; ``xz``; ``yz``) and
the table turned in equal steps through a full turn.  Write each mount as the cyclic triple
``(p, q, a)`` — xy: (x, y, z), xz: (z, x, y), yz: (y, z, x) — with ``a`` the table axis.  At table
angle θ the field in the housing frame is

    B(θ) = B_rot·(cos ψ·p̂ + sin ψ·q̂) + B_w·â,     ψ = s·θ + θ0

``B_rot`` the field in the table plane, ``B_w`` the part along the table axis, ``θ0`` where the
field lies at table zero, ``s = ±1`` the sense (which way the table axis points).  All four are
nuisance parameters of each mount: B, the dip and the table's zero need not be known, and a table
that is not level only changes ``B_rot``/``B_w`` of that mount.  Each axis' output is a sinusoid
(the seed's eq. 6)::

    o_i(θ) = a_i·cos θ + c_i·sin θ + C_i = A_i·sin(θ + b_i) + C_i,   A = √(a²+c²), b = atan2(a, c)

**Derivation of the closed form** (the seed stops at eq. 6).  Expanding ``cos ψ``, ``sin ψ``::

    a_i = k_i·B_rot·(P_i·cos θ0 + Q_i·sin θ0),   c_i = s·k_i·B_rot·(Q_i·cos θ0 − P_i·sin θ0),
    C_i = k_i·(u_i·â)·B_w + B_i0,                 P_i = u_i·p̂,  Q_i = u_i·q̂

so the complex number ``w_i = a_i + i·s·c_i = g·(M_ip + i·M_iq)`` with ``g = B_rot·e^{−iθ0}`` one
complex nuisance per mount: each mount gives two columns of ``M`` up to a complex factor.  With
``h = 1/g`` the three mounts give 18 real equations, linear and homogeneous in the 9 entries of
``M`` and the three ``h``::

    M_·x + i·M_·y = h_xy·w^xy,    M_·z + i·M_·x = h_xz·w^xz,    M_·y + i·M_·z = h_yz·w^yz

solved by the SVD (the null vector), up to one common scale (``k`` and the field appear only as a
product).  The sense ``s`` of a mount follows from its two in-plane axes: ``w_q/w_p ≈ i·k_q/k_p``.
The rotation of the whole triad about a table axis, invisible in that mount (it is ``θ0``), shows
in the other two as an amplitude of the axis that mount turns about: nothing is left unobservable.
Then the offsets and the fields along the table axes from the ``C``: ``C_i = M_ia·B_w + B_i0``
(9 equations, 6 unknowns, linear).  The scale: with a site field ``F``, ``√(B_rot² + B_w²) = F`` in
every mount; without one, the mean ``k`` is 1 and the field is measured in the probe's own unit.

The closed form starts a joint nonlinear least-squares fit of every step (``scipy.optimize.
least_squares``; ``M``, ``b`` and each mount's nuisances; the step angles too when the log does not
give them), whose covariance gives every 1σ.  It is the fit of the raw samples: a model constant over
a step sees its samples only through their mean, weighted ``n/σ²`` (:class:`Step`).  α/β come from the rows of
``M``; β means nothing when α is within 3σ of 0, and is then reported as undefined.

What the data cannot absorb: the jig (a probe tilted against the table) is indistinguishable from
the sensor's misalignment; a field that is not uniform over the turn; a table angle that is not
what the log says (each step's own angle is estimated as well, and a step off its set angle by more
than 4σ is reported).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Mount -> (p, q, a): the two marked axes in the table plane in cyclic order, and the table axis.
MOUNTS = {"xy": (0, 1, 2), "xz": (2, 0, 1), "yz": (1, 2, 0)}
#: The mounts in the order of the procedure (the calibration node's status numbers them 1..3).
MOUNT_NAMES_ORDER = tuple(MOUNTS)
AXES = "xyz"
MIN_STEPS = 8
#: β of an axis is reported only when its α exceeds this many σ.
BETA_MIN_Z = 3.0
#: A step whose estimated angle is off its set one by more than this many σ is reported (4σ: a
#: few dozen steps are checked at once).
STEP_OFF_Z = 4.0


#: Tool → table frame at table angle 0 for each mount (NED-like: the table axis down, the mount's
#: first in-plane axis p north, q east).
MOUNT_FRAME = {"xy": np.eye(3),
               "xz": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
               "yz": np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])}


def table_rotation(mount: str, table_deg: float, tilt_deg: float = 0.0) -> np.ndarray:
    """Tool → NED of a probe in ``mount`` at ``table_deg`` on a table tilted ``tilt_deg`` about
    north: ``R_tilt · Rz(θ) · R_mount`` (the table turning about its axis, down)."""
    t, c = math.radians(table_deg), math.radians(tilt_deg)
    rz = np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(c), -math.sin(c)], [0.0, math.sin(c), math.cos(c)]])
    return rx @ rz @ MOUNT_FRAME[mount]


class TurntableError(ValueError):
    """A turntable log that cannot be solved; the message names the mounting and step."""


@dataclass
class Step:
    """One held table step: ``mount``, set ``table_deg`` (NaN: not recorded), the field's ``mean``
    (3,) nT over its ``n`` samples and their per-axis ``std`` (3,), its time span and where it is
    (in a file or a stream).  The step means with weights ``n/σ²`` carry all a least-squares fit of
    a model constant over the step can take from its samples (their χ² differs by the scatter
    inside the steps only, which no parameter changes), so logs and live streams are solved alike."""

    mount: str
    table_deg: float
    mean: np.ndarray
    std: np.ndarray
    n: int
    t_start: float
    t_end: float
    where: str

    @classmethod
    def from_station(cls, st, mount: str, table_deg: float = float("nan"), where: str = "") -> "Step":
        return cls(mount, float(table_deg), np.asarray(st.b, float).copy(), np.asarray(st.b_std, float).copy(),
                   int(st.n), float(st.t_start), float(st.t_end), where or f"step at {st.where}")


# ---------------------------------------------------------------------------------------------
# Reading a log into steps
# ---------------------------------------------------------------------------------------------
def steps_from_log(log, path: str = "<log>", detector=None) -> tuple:
    """The held steps of a turntable log (:class:`probelog.ProbeLog`), each with its mount and set
    angle from the labels of its rows; returns ``(steps, messages)``.

    Steps are found by the live nodes' static detector; their rows' ``mount`` / ``table_deg``
    labels name them.  A step whose rows carry two mounts or two angles, a step in which the probe
    moved, or a hold without a mount label raise :class:`TurntableError` naming it."""
    from ..detect.gates import apply_gates
    from ..io.probelog import segment_stations

    if not log.is_turntable:
        raise TurntableError(f"{path}: not a turntable log: no 'mount' and 'table_deg' columns (or none filled)")
    stations, problems = segment_stations(log, detector, use_labels=False)
    steps, messages = [], list(problems)
    for st in stations:
        i0, i1 = np.searchsorted(log.t_s, [st.t_start, st.t_end])
        i1 = min(i1 + 1, len(log))
        mounts = {m for m in log.mount[i0:i1] if m}
        angles = {round(float(v), 6) for v in log.table_deg[i0:i1] if np.isfinite(v)}
        where = f"{path}: step at {st.where}"
        if len(mounts) > 1:
            raise TurntableError(f"{where}: its rows are labelled with mounts {', '.join(sorted(mounts))} but the "
                                 "probe did not move between them: mixed-up mount labels")
        seen = mount_of_gravity(st.g)
        if not mounts:
            if seen is None:
                messages.append(f"{where}: no mount label, and no marked axis is vertical: left out")
                continue
            mounts = {seen}
            messages.append(f"{where}: no mount label: mount {seen} (gravity along marked {AXES[MOUNTS[seen][2]]})")
        mount = mounts.pop()
        if seen is not None and seen != mount:
            raise TurntableError(f"{where}: labelled mount {mount}, but gravity lies along marked {AXES[MOUNTS[seen][2]]} "
                                 f"(mount {seen}): the mount labels look mixed up")
        if len(angles) > 1:
            raise TurntableError(f"{where} (mount {mount}): its rows give table angles "
                                 f"{', '.join(f'{a:g}' for a in sorted(angles))} without motion between them")
        apply_gates(st)
        if st.moved:
            raise TurntableError(f"{where} (mount {mount}, table {next(iter(angles), float('nan')):g}°): the probe moved "
                                 "during the step — hold it still, or cut the step out")
        steps.append(Step.from_station(st, mount, angles.pop() if angles else float("nan"), where))
    # one set angle found as several holds: the detector cut the step where the probe moved
    seen = {}
    for st in steps:
        if np.isfinite(st.table_deg):
            seen.setdefault((st.mount, round(st.table_deg, 6)), []).append(st)
    for (m, a), parts in seen.items():
        if len(parts) > 1:
            raise TurntableError(f"{path}: mount {m}, table {a:g}°: the step was found as {len(parts)} holds ("
                                 + "; ".join(p.where.split(": step at ")[-1] for p in parts)
                                 + "): the probe moved during the step — hold it still, or cut the step out")
    check_steps(steps, path)
    return steps, messages


#: A step is in a mount when gravity lies within this angle of one marked axis (the table axis).
MOUNT_TOLERANCE_DEG = 10.0


def mount_of_gravity(g) -> str | None:
    """The mount whose table axis gravity lies along (within :data:`MOUNT_TOLERANCE_DEG`), or None."""
    g = np.asarray(g, float)
    n = float(np.linalg.norm(g))
    if not np.all(np.isfinite(g)) or n == 0:
        return None
    a = int(np.argmax(np.abs(g)))
    if abs(g[a]) / n < math.cos(math.radians(MOUNT_TOLERANCE_DEG)):
        return None
    return next(m for m, (_, _, ax) in MOUNTS.items() if ax == a)


def coverage_deg(steps, mount: str) -> float:
    """How much of a full turn the steps of ``mount`` cover (deg): 360 minus the largest gap between
    the in-plane field directions of the steps (about their mean)."""
    ms = [s for s in steps if s.mount == mount]
    if len(ms) < 3:
        return 0.0
    p, q, _ = MOUNTS[mount]
    v = np.array([s.mean for s in ms])
    c = v.mean(axis=0)
    ang = np.sort(np.degrees(np.arctan2(v[:, q] - c[q], v[:, p] - c[p])) % 360.0)
    gaps = np.diff(np.concatenate([ang, [ang[0] + 360.0]]))
    return float(360.0 - gaps.max())


def check_steps(steps, path: str = "<log>") -> None:
    """Every mount present with at least :data:`MIN_STEPS` steps; set angles all given or none per
    mount; no two steps at one set angle."""
    for m in MOUNTS:
        ms = [s for s in steps if s.mount == m]
        if not ms:
            raise TurntableError(f"{path}: mount {m} is missing (the method needs all three: xy, xz, yz)")
        if len(ms) < MIN_STEPS:
            raise TurntableError(f"{path}: mount {m} has {len(ms)} steps; at least {MIN_STEPS} over a full turn are "
                                 "needed")
        given = [np.isfinite(s.table_deg) for s in ms]
        if any(given) and not all(given):
            bad = next(s for s, g in zip(ms, given) if not g)
            raise TurntableError(f"{bad.where} (mount {m}): no table angle while the mount's other steps have one")
        if all(given):
            a = np.mod([s.table_deg for s in ms], 360.0)
            dup = [x for x in set(np.round(a, 6)) if np.sum(np.round(a, 6) == x) > 1]
            if dup:
                raise TurntableError(f"{path}: mount {m}: two steps at table angle {dup[0]:g}°")


# ---------------------------------------------------------------------------------------------
# Sinusoids and the closed form
# ---------------------------------------------------------------------------------------------
@dataclass
class Sinusoid:
    """``o(θ) = A·sin(θ + b) + C`` of one axis in one mount (nT, deg), with the 1σ of A, b, C
    and the RMS of the step means about it."""

    mount: str
    axis: str
    A: float
    b_deg: float
    C: float
    rms: float
    a: float = 0.0        # coefficient of cos θ
    c: float = 0.0        # coefficient of sin θ
    std: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"mount": self.mount, "axis": self.axis, "A": self.A, "b_deg": self.b_deg, "C": self.C,
                "rms": self.rms, "std": self.std}

    def predict(self, theta_deg) -> np.ndarray:
        return self.A * np.sin(np.radians(theta_deg) + math.radians(self.b_deg)) + self.C


def check_mounts(sinusoids, steps=()) -> None:
    """Each mount must turn about its own table axis: that axis' output barely changes over the
    turn (its amplitude the smallest of the three by far).  Mount labels that do not match the data
    raise :class:`TurntableError` naming the mount and the axis the data turn about."""
    for m, (p, q, a) in MOUNTS.items():
        amp = {s.axis: s.A for s in sinusoids if s.mount == m}
        low = min(amp, key=amp.get)
        if low != AXES[a] or amp[AXES[a]] > 0.5 * min(amp[AXES[p]], amp[AXES[q]]):
            first = next((s.where for s in steps if s.mount == m), m)
            raise TurntableError(f"{first}: the steps labelled mount {m} turn about marked {low} (its output changes "
                                 f"least: amplitudes x {amp['x']:.0f}, y {amp['y']:.0f}, z {amp['z']:.0f}), not about "
                                 f"{AXES[a]}: the mount labels look mixed up")


def predicted_sinusoid(mount: str, axis: str, matrix, bias, nuis: Nuisance) -> tuple:
    """``(a, c, C)`` of one axis in one mount predicted from the model's parameters by the
    derivation in the module docstring (coefficients of cos θ, sin θ and 1)."""
    p, q, a = MOUNTS[mount]
    i = AXES.index(axis)
    t0 = math.radians(nuis.theta0_deg)
    mp, mq, ma = matrix[i, p], matrix[i, q], matrix[i, a]
    return (nuis.b_rot * (mp * math.cos(t0) + mq * math.sin(t0)),
            nuis.sense * nuis.b_rot * (mq * math.cos(t0) - mp * math.sin(t0)),
            ma * nuis.b_w + bias[i])


def step_angles(steps) -> np.ndarray:
    """The set angles (deg), or for a mount without them equal steps in the order taken."""
    out = np.empty(len(steps))
    for m in MOUNTS:
        idx = [i for i, s in enumerate(steps) if s.mount == m]
        given = np.array([steps[i].table_deg for i in idx])
        out[idx] = given if np.all(np.isfinite(given)) else 360.0 * np.arange(len(idx)) / len(idx)
    return out


def fit_sinusoids(steps, angles_deg=None) -> list:
    """The nine sinusoids: per mount and axis, linear least squares of the step means on
    ``cos θ, sin θ, 1`` (σ from the scatter about the fit)."""
    th = np.radians(step_angles(steps) if angles_deg is None else angles_deg)
    out = []
    for m in MOUNTS:
        idx = [i for i, s in enumerate(steps) if s.mount == m]
        x = np.column_stack([np.cos(th[idx]), np.sin(th[idx]), np.ones(len(idx))])
        y = np.array([steps[i].mean for i in idx])
        coef, *_ = np.linalg.lstsq(x, y, rcond=None)
        res = y - x @ coef
        dof = max(len(idx) - 3, 1)
        cov_unit = np.linalg.inv(x.T @ x)
        for j in range(3):
            a, c, cc = coef[:, j]
            s2 = float(res[:, j] @ res[:, j]) / dof
            cv = cov_unit * s2
            amp = math.hypot(a, c)
            # σ of A and b from those of a and c
            ja = np.array([a, c]) / amp if amp > 0 else np.zeros(2)
            jb = np.array([c, -a]) / amp ** 2 if amp > 0 else np.zeros(2)
            sa = math.sqrt(max(ja @ cv[:2, :2] @ ja, 0.0))
            sb = math.degrees(math.sqrt(max(jb @ cv[:2, :2] @ jb, 0.0)))
            out.append(Sinusoid(m, AXES[j], amp, math.degrees(math.atan2(a, c)), float(cc),
                                math.sqrt(float(res[:, j] @ res[:, j]) / len(idx)), float(a), float(c),
                                {"A": sa, "b_deg": sb, "C": math.sqrt(cv[2, 2])}))
    return out


@dataclass
class Nuisance:
    """One mount's field and table: ``b_rot``, ``b_w`` (nT, or the probe's unit without a site),
    ``theta0_deg`` (where the in-plane field lies at table zero) and ``sense`` (±1)."""

    b_rot: float
    b_w: float
    theta0_deg: float
    sense: int


def closed_form(sinusoids, field_nt: float | None = None) -> tuple:
    """``(M, bias, {mount: Nuisance})`` from the nine sinusoids (module docstring)."""
    sn = {(s.mount, s.axis): s for s in sinusoids}
    w, sense = {}, {}
    for m, (p, q, a) in MOUNTS.items():
        wp = complex(sn[(m, AXES[p])].a, sn[(m, AXES[p])].c)
        wq = complex(sn[(m, AXES[q])].a, sn[(m, AXES[q])].c)
        s = 1 if (wq / wp).imag > 0 else -1
        sense[m] = s
        w[m] = np.array([complex(sn[(m, ax)].a, s * sn[(m, ax)].c) for ax in AXES])
    # unknowns: M (9, row-major M[i, j] at 3i + j), then Re h, Im h of xy, xz, yz
    rows = []
    for k, (m, (p, q, a)) in enumerate(MOUNTS.items()):
        hr, hi = 9 + 2 * k, 10 + 2 * k
        scale = 1.0 / np.mean(np.abs(w[m]))
        for i in range(3):
            wr, wi = w[m][i].real * scale, w[m][i].imag * scale
            r1 = np.zeros(15)                     # M_ip = Re(h·w_i) = hr·wr − hi·wi
            r1[3 * i + p], r1[hr], r1[hi] = 1.0, -wr, wi
            r2 = np.zeros(15)                     # M_iq = Im(h·w_i) = hr·wi + hi·wr
            r2[3 * i + q], r2[hr], r2[hi] = 1.0, -wi, -wr
            rows += [r1, r2]
    _, _, vt = np.linalg.svd(np.array(rows))
    x = vt[-1]
    mat = x[:9].reshape(3, 3)
    if np.sum(np.diag(mat)) < 0:
        mat = -mat
    # offsets and fields along the table axes: C_i = M_ia·B_w + b_i
    amat, rhs = [], []
    for k, (m, (p, q, a)) in enumerate(MOUNTS.items()):
        for i in range(3):
            r = np.zeros(6)
            r[i], r[3 + k] = 1.0, mat[i, a]
            amat.append(r)
            rhs.append(sn[(m, AXES[i])].C)
    sol, *_ = np.linalg.lstsq(np.array(amat), np.array(rhs), rcond=None)
    bias, b_w = sol[:3], sol[3:]
    nuis = {}
    for k, (m, (p, q, a)) in enumerate(MOUNTS.items()):
        # h = 1/g from the columns now known: M_·p + i·M_·q = h·w  (least squares over the axes)
        lhs = mat[:, p] + 1j * mat[:, q]
        h = complex(np.vdot(w[m], lhs) / np.vdot(w[m], w[m]))
        nuis[m] = Nuisance(1.0 / abs(h), float(b_w[k]), math.degrees(math.atan2(h.imag, h.real)), sense[m])
    # the scale (k and the field appear only as a product): the field's magnitude is the site's in
    # every mount, or the mean k is 1 — M → M/f, fields → f·fields
    mag = float(np.mean([math.hypot(n.b_rot, n.b_w) for n in nuis.values()]))
    f = field_nt / mag if field_nt else float(np.mean(np.linalg.norm(mat, axis=1)))
    mat_out = mat / f
    for n in nuis.values():
        n.b_rot, n.b_w = n.b_rot * f, n.b_w * f
    return mat_out, bias, nuis


# ---------------------------------------------------------------------------------------------
# α, β and the joint refinement
# ---------------------------------------------------------------------------------------------
def angles_from_matrix(mat) -> dict:
    """``k``, ``α`` (deg), ``β`` (deg) of each axis and ``U − I`` from ``M = diag(k)·U``."""
    mat = np.asarray(mat, float)
    k = np.linalg.norm(mat, axis=1)
    u = mat / k[:, None]
    alpha = np.degrees(np.arccos(np.clip(np.diag(u), -1.0, 1.0)))
    beta = np.degrees([math.atan2(u[0, 2], u[0, 1]), math.atan2(u[1, 0], u[1, 2]), math.atan2(u[2, 1], u[2, 0])])
    return {"k": k, "alpha_deg": alpha, "beta_deg": beta, "misalignment_rad": u - np.eye(3)}


def field_at(theta_deg, mount: str, nuis: Nuisance) -> np.ndarray:
    """(N, 3) housing-frame field of ``mount`` at table angles ``theta_deg``."""
    p, q, a = MOUNTS[mount]
    psi = nuis.sense * np.radians(theta_deg) + math.radians(nuis.theta0_deg)
    out = np.zeros((len(np.atleast_1d(theta_deg)), 3))
    out[:, p] = nuis.b_rot * np.cos(psi)
    out[:, q] = nuis.b_rot * np.sin(psi)
    out[:, a] = nuis.b_w
    return out


@dataclass
class TurntableResult:
    """The turntable calibration of the magnetometer: ``M`` (= K·E) and ``bias`` (nT) with their
    covariance, each mount's nuisances, the sinusoids, the residual RMS (nT) and what to say."""

    matrix: np.ndarray
    bias: np.ndarray
    cov: np.ndarray                 # of [M row-major (9), bias (3)]
    nuisance: dict
    sinusoids: list
    residual_rms_nt: float
    field_nt: float
    scale_known: bool
    step_angles_deg: np.ndarray
    step_offsets: list = field(default_factory=list)   # steps off their set angle: (where, Δ deg, σ deg)
    messages: list = field(default_factory=list)
    closed: tuple | None = None     # the closed form's (M, bias)

    def parameters(self) -> dict:
        """k, bias, α, β (deg) and U − I with 1σ (propagated from the covariance numerically)."""
        x0 = np.concatenate([self.matrix.ravel(), self.bias])

        def vec(x):
            d = angles_from_matrix(x[:9].reshape(3, 3))
            return np.concatenate([d["k"], x[9:], d["alpha_deg"], d["beta_deg"],
                                   d["misalignment_rad"].ravel()])

        y0 = vec(x0)
        jac = np.zeros((len(y0), 12))
        for j in range(12):
            h = max(abs(x0[j]) * 1e-7, 1e-9)
            x = x0.copy()
            x[j] += h
            dy = vec(x) - y0
            dy[9:12] = (dy[9:12] + 180.0) % 360.0 - 180.0      # β wraps
            jac[:, j] = dy / h
        sd = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", jac, self.cov, jac), 0.0))
        d = angles_from_matrix(self.matrix)
        out = {"k": d["k"], "k_std": sd[0:3], "bias_nT": self.bias, "bias_std": sd[3:6],
               "alpha_deg": d["alpha_deg"], "alpha_std": sd[6:9], "beta_deg": d["beta_deg"].copy(),
               "beta_std": sd[9:12], "misalignment_rad": d["misalignment_rad"],
               "misalignment_std": sd[12:21].reshape(3, 3), "beta_defined": np.ones(3, bool)}
        # α is the length of the off-diagonal pair of its row; β means nothing when it is noise
        for i in range(3):
            off = [j for j in range(3) if j != i]
            comp_sd = float(np.sqrt(np.mean(out["misalignment_std"][i, off] ** 2)))
            if math.radians(out["alpha_deg"][i]) < BETA_MIN_Z * comp_sd:
                out["beta_defined"][i] = False
                out["beta_deg"][i] = float("nan")
                out["beta_std"][i] = float("nan")
        return out

    def to_json(self) -> dict:
        p = self.parameters()

        def lst(x):
            return [None if not np.isfinite(v) else float(v) for v in np.ravel(x)]

        return {"mag": {"k": lst(p["k"]), "k_std": lst(p["k_std"]), "bias_nT": lst(p["bias_nT"]),
                        "bias_std": lst(p["bias_std"]), "alpha_deg": lst(p["alpha_deg"]),
                        "alpha_std": lst(p["alpha_std"]), "beta_deg": lst(p["beta_deg"]),
                        "beta_std": lst(p["beta_std"]),
                        "misalignment_rad": [lst(r) for r in p["misalignment_rad"]],
                        "misalignment_std": [lst(r) for r in p["misalignment_std"]],
                        "matrix": [lst(r) for r in self.matrix]},
                "sinusoids": [s.to_json() for s in self.sinusoids],
                "residual_rms_nT": float(self.residual_rms_nt), "field_nT": float(self.field_nt),
                "scale": "absolute (site field)" if self.scale_known else "relative (no site: mean k = 1)",
                "mounts": {m: {"b_rot": float(n.b_rot), "b_w": float(n.b_w), "theta0_deg": float(n.theta0_deg),
                               "sense": int(n.sense),
                               "dip_if_level_deg": math.degrees(math.atan2(abs(n.b_w), abs(n.b_rot)))}
                           for m, n in self.nuisance.items()},
                "step_offsets": [{"step": w, "offset_deg": float(d), "std_deg": float(s)} for w, d, s in self.step_offsets],
                "messages": self.messages}


def solve(steps, field_nt: float | None = None, free_angles: bool | None = None) -> TurntableResult:
    """Calibrate the magnetometer from turntable steps (:func:`steps_from_log`).

    ``field_nt``: the site's total field (absolute ``k``); None: relative ``k`` (mean 1).
    ``free_angles``: estimate every step's angle (default: when the log does not give them)."""
    from scipy.optimize import least_squares   # here: scipy.optimize costs the calibration node's start 0.27 s

    check_steps(steps)
    given = np.all([np.isfinite(s.table_deg) for s in steps])
    free = (not given) if free_angles is None else bool(free_angles)
    theta = step_angles(steps)
    sins = fit_sinusoids(steps, theta)
    check_mounts(sins, steps)
    mat0, bias0, nuis0 = closed_form(sins, field_nt)
    mounts = list(MOUNTS)
    # the noise per axis: the pooled scatter inside the steps; each step mean weighs n/σ²
    n_s = np.array([s.n for s in steps], float)
    sigma = np.sqrt(np.sum([(s.n - 1) * np.nan_to_num(s.std) ** 2 for s in steps], axis=0) / max(np.sum(n_s - 1), 1))
    sigma = np.where(sigma > 0, sigma, 1.0)
    means = np.array([s.mean for s in steps])
    weight = np.sqrt(n_s)[:, None] / sigma
    mount_of = np.array([mounts.index(s.mount) for s in steps])
    first = {m: next(i for i, s in enumerate(steps) if s.mount == m) for m in mounts}
    free_idx = [i for i in range(len(steps)) if free and i != first[steps[i].mount]]

    def unpack(x):
        mat = x[:9].reshape(3, 3)
        b = x[9:12]
        nu = {m: Nuisance(x[12 + 3 * k], x[13 + 3 * k], x[14 + 3 * k], nuis0[m].sense) for k, m in enumerate(mounts)}
        th = theta.copy()
        if free_idx:
            th[free_idx] = x[21:]
        return mat, b, nu, th

    def model_means(x):
        mat, b, nu, th = unpack(x)
        out = np.empty((len(steps), 3))
        for k, m in enumerate(mounts):
            sel = mount_of == k
            out[sel] = field_at(th[sel], m, nu[m]) @ mat.T + b
        return out

    def fun(x):
        r = ((means - model_means(x)) * weight).ravel()
        mat, _, nu, _ = unpack(x)
        if field_nt:       # the field's magnitude in every mount is the site's
            g = [(math.hypot(n.b_rot, n.b_w) - field_nt) / (1e-6 * field_nt) for n in nu.values()]
        else:              # the scale gauge: mean k = 1
            g = [(np.mean(np.linalg.norm(mat, axis=1)) - 1.0) / 1e-9]
        return np.concatenate([r, g])

    x0 = np.concatenate([mat0.ravel(), bias0, *[[nuis0[m].b_rot, nuis0[m].b_w, nuis0[m].theta0_deg] for m in mounts],
                         theta[free_idx]])
    fscale = field_nt or float(np.mean([math.hypot(n.b_rot, n.b_w) for n in nuis0.values()]))
    xs = np.concatenate([np.full(9, 1e-3), np.full(3, 10.0), np.tile([fscale * 1e-3, fscale * 1e-3, 0.1], 3),
                         np.full(len(free_idx), 0.1)])
    res = least_squares(fun, x0, x_scale=xs, method="trf", jac="2-point", xtol=1e-12, ftol=1e-12, gtol=1e-12,
                        max_nfev=200)
    mat, b, nu, th = unpack(res.x)
    n_data = means.size
    chi2 = float(np.sum(res.fun[:n_data] ** 2))
    red = max(chi2 / max(n_data - len(res.x), 1), 1.0)
    # the covariance from the Jacobian's SVD (the gauge rows included: they fix the scale)
    _, sv, vt = np.linalg.svd(res.jac, full_matrices=False)
    keep = sv > sv[0] * 1e-12
    cov_all = (vt[keep].T / sv[keep] ** 2) @ vt[keep] * red
    # the samples' RMS about the model: the scatter inside the steps and the steps' misfit
    resid2 = (np.sum((n_s - 1)[:, None] * np.array([np.nan_to_num(s.std) ** 2 for s in steps]))
              + np.sum(n_s[:, None] * (means - model_means(res.x)) ** 2)) / (3 * np.sum(n_s))
    out = TurntableResult(matrix=mat, bias=b, cov=cov_all[:12, :12], nuisance=nu, sinusoids=sins,
                          residual_rms_nt=float(np.sqrt(resid2)),
                          field_nt=float(field_nt) if field_nt else float(np.mean([math.hypot(n.b_rot, n.b_w)
                                                                                  for n in nu.values()])),
                          scale_known=bool(field_nt), step_angles_deg=th, closed=(mat0, bias0))
    if free and given:
        sd = np.sqrt(np.diag(cov_all)[21:])
        for j, i in enumerate(free_idx):
            d = th[i] - theta[i]
            if abs(d) > STEP_OFF_Z * sd[j]:
                out.step_offsets.append((steps[i].where, float(d), float(sd[j])))
    if not field_nt:
        out.messages.append("no site field given: k is relative (mean 1) and the field is in the probe's own unit; "
                            "azimuths are unaffected by a common scale")
    return out


def check_angles(steps, field_nt=None) -> list:
    """Steps whose data put them off their set angle by more than 3σ (the table was not where the
    log says): ``[(where, Δ deg, σ deg)]``, from a fit with every step's angle free."""
    if not all(np.isfinite(s.table_deg) for s in steps):
        return []
    return solve(steps, field_nt, free_angles=True).step_offsets


def record(res: TurntableResult, acc_cal=None, site=None, probe_id: str = "probe", warn=None):
    """The calibration record (:class:`coeffs.Calibration`) of a turntable result: the magnetometer
    as the base model's ``K·E`` and bias (:meth:`errormodel.TriadModel.from_matrix`); the
    accelerometer (and its effects) from ``acc_cal`` (e.g. the twelve positions' record), else
    identity and said not identifiable.  The site: ``site``, else ``acc_cal``'s, else what the
    turntable measures (the field in the probe's unit, the dip if the table was level, declination
    unknown: 0), said through ``warn``."""
    from ..core.coeffs import Calibration
    from ..core.errormodel import TriadModel
    from ..core.frames import Site
    from ..core.model import ProbeModel

    say = warn or (lambda m: None)
    mag = TriadModel.from_matrix(res.matrix, res.bias)
    not_id = []
    if acc_cal is not None:
        model = ProbeModel.base(acc_cal.acc, mag)
        for t in acc_cal.model.extra_terms:
            if t.effect.sensor == "acc":
                model = model.with_effect(t.effect, t.scope)
    else:
        model = ProbeModel.base(None, mag)
        not_id.append({"parameter": "acc", "reason": "the turntable procedure calibrates the magnetometer only: the "
                                                     "accelerometer is identity here — combine with an accelerometer "
                                                     "calibration (turntable --acc RECORD)"})
    if site is not None:
        rec_site, source = site, "given"
    elif acc_cal is not None:
        rec_site, source = acc_cal.site, acc_cal.site_source
        say(f"no site given: the record takes the accelerometer record's site reference ({acc_cal.site_source})")
    else:
        dip = float(np.degrees(np.mean([math.atan2(abs(n.b_w), abs(n.b_rot)) for n in res.nuisance.values()])))
        rec_site, source = Site(res.field_nt, dip, 0.0), "measured"
        say(f"no site given: the record's site is what the turntable measures — total field {res.field_nt:.1f} (the "
            f"probe's unit: k is relative), dip {dip:.3f}° if the table was level, declination unknown (0): give a "
            "site for surveys")
    method = "turntable" + (f" + {acc_cal.method} (accelerometer)" if acc_cal is not None else "")
    return Calibration(model, probe_id=probe_id, method=method, site=rec_site, site_source=source,
                       diagnostics={"turntable": res.to_json()}, not_identifiable=not_id)


#: A mount is complete with at least MIN_STEPS steps whose largest gap is at most 360° − this.
COMPLETE_COVERAGE_DEG = 300.0


@dataclass
class TurntableSession:
    """The turntable procedure live (the calibration node's ``method:=turntable``): static holds
    (:class:`station.Station`, from the live detector) are offered one by one; the mount of each is
    the one gravity shows (or ``mount``, set by the operator); a mount is complete with
    :data:`MIN_STEPS` steps covering the turn (:func:`coverage_deg`); when all three are, the steps'
    angles are estimated with the calibration (:func:`solve`, free angles: a stream has no table
    angles) and the record made (:func:`record`).  Every refusal is said (``warnings``)."""

    site: object = None
    acc_cal: object = None
    probe_id: str = "probe"
    mount: str = ""
    steps: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    infos: list = field(default_factory=list)
    state: str = "collecting"
    message: str = ""
    solves: int = 0
    calibration: object = None
    result: object = None
    _solved_with: int = 0

    def progress(self) -> dict:
        """Per mount: ``(steps, coverage deg, complete)``."""
        out = {}
        for m in MOUNTS:
            n = sum(s.mount == m for s in self.steps)
            cov = coverage_deg(self.steps, m)
            out[m] = (n, cov, n >= MIN_STEPS and cov >= COMPLETE_COVERAGE_DEG)
        return out

    def progress_text(self) -> str:
        return "; ".join(f"mount {m}: {n} steps, {cov:.0f}° of the turn" + (" (complete)" if ok else "")
                         for m, (n, cov, ok) in self.progress().items())

    def identify(self, g) -> str | None:
        return self.mount or mount_of_gravity(g)

    def offer(self, st) -> str:
        """Take one closed static hold; returns ``accepted`` or ``rejected``."""
        from ..detect.gates import apply_gates

        apply_gates(st)
        where = f"step at {st.where}"
        if st.short:
            return "rejected"
        if st.moved or st.unusable:
            self.warnings.append(f"{where}: " + ("the probe moved during the step" if st.moved else
                                                 f"a gate refused the {' and '.join(st.unusable)} data")
                                 + ": not used")
            return "rejected"
        seen = mount_of_gravity(st.g)
        mount = self.mount or seen
        if mount is None:
            self.warnings.append(f"{where}: no marked axis is vertical (gravity {np.round(st.g, 2).tolist()} m/s²): not "
                                 "a turntable mounting, not used")
            return "rejected"
        if self.mount and seen is not None and seen != self.mount:
            self.warnings.append(f"{where}: the mount is set to {self.mount} but gravity lies along marked "
                                 f"{AXES[MOUNTS[seen][2]]} (mount {seen}): taken as {self.mount}, as set")
        self.steps.append(Step.from_station(st, mount, where=where))
        prog = self.progress()
        self.infos.append(f"{where}: mount {mount}, step {prog[mount][0]} ({prog[mount][1]:.0f}° of the turn)")
        if self.state != "done" and all(ok for *_, ok in prog.values()):
            self.solve()
        return "accepted"

    def solve(self) -> None:
        try:
            res = solve(self.steps, self.site.total_field_nt if self.site is not None else None, free_angles=True)
        except (TurntableError, np.linalg.LinAlgError, ValueError) as exc:
            self.state, self.message = "error", f"turntable calibration failed: {exc}"
            return
        self.result = res
        self.calibration = record(res, self.acc_cal, self.site, self.probe_id, warn=self.warnings.append)
        self.solves += 1
        self._solved_with = len(self.steps)
        p = res.parameters()
        self.state = "done"
        self.message = (f"turntable solved from {len(self.steps)} steps: residual {res.residual_rms_nt:.1f} nT; "
                        "alpha " + ", ".join(f"{a} {v:.3f}±{sd:.3f}°" for a, v, sd in
                                             zip(AXES, p["alpha_deg"], p["alpha_std"])))

    def finish(self) -> None:
        """The end of the data: solve with what there is (again, if steps came after a solve), or
        say which mount is short of what."""
        if self.state == "done" and self._solved_with == len(self.steps):
            return
        missing = [f"mount {m}: {n} steps, {cov:.0f}° of the turn" for m, (n, cov, ok) in self.progress().items()
                   if n < MIN_STEPS]
        if missing:
            self.state = "error"
            self.message = ("turntable incomplete — " + "; ".join(missing)
                            + f" (each mount needs at least {MIN_STEPS} steps over a full turn)")
            return
        self.solve()

    def reset(self) -> None:
        self.steps, self.warnings, self.infos = [], [], []
        self.state, self.message, self.calibration, self.result, self._solved_with = "collecting", "", None, None, 0
