"""A probe's calibration history (issue 13, item 3): parameters over time with 1σ, a change beyond
the combined uncertainty flagged with the parameters that moved, an overdue probe flagged — from
calibrations of simulated probes stored in the registry (SQLite and PostgreSQL)."""
import dataclasses
import datetime as dt
import math
import re

import pytest

from inclinometer_calib.calibrate import simulate as sim
from inclinometer_calib.core.errormodel import TriadModel
from inclinometer_calib.fleet import history as hi
from inclinometer_calib.fleet.registry import Registry
from inclinometer_calib.core.model import ProbeModel

UTC = dt.timezone.utc
T0 = dt.datetime(2026, 1, 10, tzinfo=UTC)
DAY = dt.timedelta(days=1)
JUMP_NT = 50.0


def with_mag_bias_jump(probe, jump_nt):
    """The same simulated probe with its magnetometer's x bias moved by ``jump_nt`` (a knock)."""
    m = probe.mag
    return dataclasses.replace(probe, model=ProbeModel.base(
        probe.acc, TriadModel(scale=m.scale, bias=m.bias + [jump_nt, 0.0, 0.0], e=m.e)))


@pytest.fixture(scope="module")
def cals(calibrate):
    """Probe SN-H calibrated three times: #1, #2 the same probe (a re-calibration), #3 after a
    50 nT jump of its magnetometer's x bias."""
    probe = sim.build_probe(5)
    return [calibrate(probe, "SN-H", 1), calibrate(probe, "SN-H", 2),
            calibrate(with_mag_bias_jump(probe, JUMP_NT), "SN-H", 3)]


@pytest.fixture
def reg(db_url, cals):
    with Registry(db_url) as r:
        r.add_probe("SN-H", model="MX-3", calibration_interval_days=60)
        for k, c in enumerate(cals):
            r.add_calibration(c, calibrated_at=T0 + 30 * k * DAY, operator_note=f"stand 2, run {k + 1}")
        yield r


def test_a_bias_jump_is_flagged_naming_mag_bias_and_a_recalibration_is_not(reg):
    h = hi.analyse(reg.probe("SN-H"), reg.history("SN-H"), at=T0 + 61 * DAY)
    assert [c.index for c in h.changes] == [1, 2]
    recal, jump = h.changes
    assert not recal.flagged                                   # #2: the same probe, calibrated again
    assert [m.parameter.label for m in jump.moves] == ["mag bias_x"]
    (m,) = jump.moves
    assert m.delta == pytest.approx(JUMP_NT, abs=5 * m.sigma)
    assert m.z > 20
    assert "magnetometer bias shift" in jump.reading()
    # the non-orthogonality terms carry no σ: listed as not tested, never flagged
    assert sorted(jump.untested) == sorted(f"{s} {e}" for s in ("acc", "mag")
                                           for e in ("e_yx", "e_zx", "e_xy", "e_zy", "e_xz", "e_yz"))


def test_the_rule_is_k_times_the_combined_sigma(reg):
    entries = reg.history("SN-H")
    h = hi.analyse(reg.probe("SN-H"), entries, at=T0)
    m = h.changes[1].moves[0]
    va, sa = hi.value_and_sigma(entries[1], m.parameter)
    vb, sb = hi.value_and_sigma(entries[2], m.parameter)
    assert m.sigma == pytest.approx(math.hypot(sa, sb)) and m.delta == pytest.approx(vb - va)
    just_below, just_above = m.z * 0.999, m.z * 1.001
    assert [x.parameter.label for x in hi.analyse(reg.probe("SN-H"), entries, k=just_below).changes[1].moves] == \
        ["mag bias_x"]
    assert "mag bias_x" not in [x.parameter.label for x in
                                hi.analyse(reg.probe("SN-H"), entries, k=just_above).changes[1].moves]
    with pytest.raises(ValueError, match="positive"):
        hi.analyse(reg.probe("SN-H"), entries, k=0)


def test_overdue_at_the_date_asked(reg):
    last = T0 + 60 * DAY
    assert hi.analyse(reg.probe("SN-H"), reg.history("SN-H"), at=last + 59 * DAY).overdue is None
    od = hi.analyse(reg.probe("SN-H"), reg.history("SN-H"), at=last + 75 * DAY).overdue
    assert od is not None and od.age_days == pytest.approx(75) and od.interval_days == 60
    assert od.describe() == ("OVERDUE at 2026-05-25: last calibrated 2026-03-11, 75 days ago, beyond the calibration "
                             "interval of 60 days (due 2026-05-10)")
    reg.add_probe("SN-NEW")
    never = hi.analyse(reg.probe("SN-NEW"), reg.history("SN-NEW"), at=T0)
    assert never.overdue is not None and "never calibrated" in never.overdue.describe()


def test_text_table_and_html(reg, cals, db_url):
    h = hi.analyse(reg.probe("SN-H"), reg.history("SN-H"), at=T0 + 200 * DAY)
    text = hi.format_history(h)
    row = next(ln for ln in text.splitlines() if ln.startswith("mag bias_x"))
    cells = row.split()
    assert cells[-1] == "*" and len(re.findall(r"-?\d+\.\d+±\d+\.\d+", row)) == 3     # 3 dates, value±σ, moved
    v, s = hi.value_and_sigma(reg.history("SN-H")[0], hi.Parameter("mag", "bias_x", "bias", "nT", ("bias", 0)))
    assert f"{v:.2f}±{s:.2f}" in row and s == pytest.approx(cals[0].uncertainty["mag"]["bias"][0])
    assert "FLAG #3 2026-03-11" in text and "mag bias_x" in text.split("FLAG #3")[1]
    assert "FLAG #2" not in text
    assert "OVERDUE at 2026-07-29" in text
    if not db_url.startswith("sqlite"):
        return   # the page is drawn from the History the text above pins for each database: once (2 s)
    page = hi.to_html(h)
    assert page.count("<img") == 2 and page.count("data:image/png;base64,") == 2
    assert "moved beyond 3σ combined" in page and "OVERDUE" in page
