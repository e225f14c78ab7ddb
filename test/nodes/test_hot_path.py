"""common.HotPathExecutor, the executor the correction node runs on as a process: its sample streams
on a wait set of their own, drained in batches, everything else as rclpy serves it.

Over real DDS in the test's own domain (rclpy in-process): the node spun by it gives the same
stations and the same corrected samples as the node's callbacks called directly, message by
message; the timer (the idle flush closes the last station) and the parameter services go on;
an error in a sample callback ends the spin with that error; shutdown stops its thread.  ``spin``
(every node's loop) ends quietly on a stop signal that lands mid-step."""
import math
import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="ROS 2 tests need `bash scripts/setup.sh` and `source scripts/env.sh`")

from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import Imu, MagneticField, Temperature  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from inclinometer_calib.calibrate import simulate as sim  # noqa: E402
from inclinometer_calib.core.coeffs import Calibration  # noqa: E402
from inclinometer_calib.core.frames import Site  # noqa: E402
from inclinometer_calib.msg import SurveyStation  # noqa: E402
from inclinometer_calib.nodes import common as c  # noqa: E402
from inclinometer_calib.nodes.correction import CorrectionNode  # noqa: E402
from inclinometer_calib.core.station import Station  # noqa: E402


class _Collect:
    def __init__(self):
        self.msgs = []
        self.readers = 0        # matched subscriptions, as a publisher reports them

    def publish(self, msg):
        self.msgs.append(msg)

    def get_subscription_count(self):
        return self.readers


def _spin_in_thread(executor):
    """``executor.spin()`` in a thread; returns (thread, box) where box['error'] is what it raised."""
    box = {"error": None}

    def run():
        try:
            executor.spin()
        except BaseException as exc:  # noqa: B036 — handed to the test thread
            box["error"] = exc

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th, box


def _wait(cond, timeout=20.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end and not cond():
        time.sleep(0.02)
    return cond()


def _messages(log):
    """The probe's messages of a log, as the probe publishes them (imu, mag, temperature per sample)."""
    out = []
    for k, (t, f, m) in enumerate(zip(log.t_s.tolist(), log.acc.tolist(), (log.mag * 1e-9).tolist())):
        mi, mm, mt = Imu(), MagneticField(), Temperature()
        c.set_stamp(mi.header.stamp, t)
        mm.header.stamp = mt.header.stamp = mi.header.stamp
        mi.linear_acceleration.x, mi.linear_acceleration.y, mi.linear_acceleration.z = f
        mm.magnetic_field.x, mm.magnetic_field.y, mm.magnetic_field.z = m
        mt.temperature = 25.0 + 0.01 * k
        out.append((mi, mm, mt))
    return out


def _fields(msg):
    return {k: getattr(msg, k) for k in msg.get_fields_and_field_types() if k != "header"}


def _same(a, b):
    if isinstance(a, float):
        return (math.isnan(a) and math.isnan(b)) or a == b
    if hasattr(a, "__len__") and not isinstance(a, str):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def test_the_node_on_the_hot_path_executor_gives_what_its_callbacks_give(ros, tmp_path):
    site = Site()
    cal = Calibration(acc=sim.build_probe(3).acc, mag=sim.build_probe(3).mag, probe_id="hot", site=site)
    path = tmp_path / "coeffs.yaml"
    cal.save(path)
    refs = [(30.0, 60.0, 0.0), (40.0, 120.0, 90.0), (50.0, 200.0, 120.0)]
    stations = [Station.planned(sim.orientation_matrix(*r), 2.0, ref=r) for r in refs]
    log = sim.run_session(sim.build_probe(3), site, stations, np.random.default_rng(1), rate_hz=100.0, move_s=0.5,
                          survey=True)
    msgs = _messages(log)
    params = [Parameter("coeffs_file", value=str(path)), Parameter("use_topic", value=False),
              Parameter("publish_corrected", value=True), Parameter("qos.reliability", value="reliable"),
              Parameter("qos.depth", value=5000), Parameter("idle_flush_s", value=0.5)]

    # the reference: the node's callbacks called one message at a time, as rclpy's executors call them
    direct = CorrectionNode(parameter_overrides=params, cli_args=["--ros-args", "-r", "__node:=correction_direct"])
    ros.append(direct)
    direct.pub_station, direct.pub_diag, direct.pub_imu, direct.pub_mag = _Collect(), _Collect(), _Collect(), _Collect()
    for mi, mm, mt in _messages(log):   # its own copies: the node corrects a message in place
        direct.stream._on_imu(serialize_message(mi), None)
        direct.stream._on_mag(serialize_message(mm))
        direct.stream._on_temp(serialize_message(mt))
    direct.stream.idle()                  # what the idle flush does at the end of the stream
    assert len(direct.pub_station.msgs) == 3 and len(direct.pub_imu.msgs) == len(msgs)

    node = CorrectionNode(parameter_overrides=params)
    ros.append(node)
    executor = c.HotPathExecutor(node.hot_subscriptions)
    executor.add_node(node)
    # the sample streams and their QoS events are out of the spinning thread's wait set, the rest in it
    hot = {id(s) for s in node.hot_subscriptions} | {id(e) for s in node.hot_subscriptions for e in s.event_handlers}
    # (the coefficients' topic too when it is used: use_topic is false here); the reference is taken in
    # turn with the samples too (the stream driver's side streams)
    assert {s.topic_name for s in node.hot_subscriptions} == {c.TOPIC_IMU, c.TOPIC_MAG, c.TOPIC_TEMPERATURE,
                                                                  c.TOPIC_REFERENCE, c.TOPIC_DEPTH}
    for entity in (*node.subscriptions, *node.waitables, *node.timers, *node.services):
        assert executor.can_execute(entity) == (id(entity) not in hot)
    spin_thread, box = _spin_in_thread(executor)

    feeder = rclpy.create_node("hot_path_feeder")
    ros.append(feeder)
    feed_exec = SingleThreadedExecutor()
    feed_exec.add_node(feeder)
    stop = threading.Event()
    feed_thread = threading.Thread(target=lambda: [feed_exec.spin_once(timeout_sec=0.05)
                                                   for _ in iter(stop.is_set, True)], daemon=True)
    feed_thread.start()
    try:
        qos = c.sensor_qos(5000, "reliable")
        pubs = [feeder.create_publisher(t, topic, qos) for t, topic in
                ((Imu, c.TOPIC_IMU), (MagneticField, c.TOPIC_MAG), (Temperature, c.TOPIC_TEMPERATURE))]
        got = {"imu": [], "mag": [], "station": []}
        feeder.create_subscription(Imu, c.TOPIC_IMU_CORRECTED, got["imu"].append, qos)
        feeder.create_subscription(MagneticField, c.TOPIC_MAG_CORRECTED, got["mag"].append, qos)
        feeder.create_subscription(SurveyStation, c.TOPIC_STATION, got["station"].append, c.reliable_qos(100))
        assert _wait(lambda: all(p.get_subscription_count() >= 1 for p in pubs)
                     and feeder.count_publishers(c.TOPIC_STATION) >= 1
                     and feeder.count_publishers(c.TOPIC_IMU_CORRECTED) >= 1), "no discovery"
        time.sleep(0.5)
        # the parameter services are served (by the spinning thread), while the samples flow
        client = feeder.create_client(SetParameters, "/correction/set_parameters")
        assert client.wait_for_service(timeout_sec=10.0)
        for k, (mi, mm, mt) in enumerate(msgs):
            for pub, msg in zip(pubs, (mi, mm, mt)):
                pub.publish(msg)
            if k == 10:   # (publish_short is read-only now: the engine takes it at start-up)
                fut = client.call_async(SetParameters.Request(parameters=[
                    Parameter("publish_corrected", value=True).to_parameter_msg()]))
            if k % 50 == 49:
                time.sleep(0.01)   # bursts of 50 samples: each wake-up finds a batch to drain
        assert _wait(lambda: len(got["station"]) == 3 and len(got["imu"]) == len(got["mag"]) == len(msgs)), \
            (len(got["station"]), len(got["imu"]), len(got["mag"]))
        assert fut.done() and fut.result().results[0].successful
        assert box["error"] is None and spin_thread.is_alive()
    finally:
        stop.set()
        feed_thread.join(2.0)
        feed_exec.shutdown()
    executor.shutdown()
    spin_thread.join(5.0)
    assert not spin_thread.is_alive() and not executor._hot_thread.is_alive()
    assert box["error"] is None

    # the last station came from the idle flush (the timer, in the spinning thread); all as the callbacks gave
    for a, b in zip(got["station"], direct.pub_station.msgs):
        fa, fb = _fields(a), _fields(b)
        bad = [k for k in fa if not _same(fa[k], fb[k])]
        assert not bad, {k: (fa[k], fb[k]) for k in bad}
    # every corrected sample, bit for bit, in order
    for a, b in zip(got["imu"], direct.pub_imu.msgs):
        assert (a.header.stamp, a.linear_acceleration) == (b.header.stamp, b.linear_acceleration)
    for a, b in zip(got["mag"], direct.pub_mag.msgs):
        assert (a.header.stamp, a.magnetic_field) == (b.header.stamp, b.magnetic_field)
    assert direct.pub_imu.msgs[0].linear_acceleration.x != log.acc[0, 0]   # corrected, not passed through


def test_an_error_in_a_sample_callback_ends_the_spin_with_that_error(ros):
    node = rclpy.create_node("hot_path_failing")
    ros.append(node)
    seen = []

    def on_msg(msg):
        seen.append(msg.data)
        if msg.data == "boom":
            raise RuntimeError("sample callback failed on 'boom'")

    sub = node.create_subscription(String, "/hot_path_test", on_msg, c.reliable_qos(10))
    executor = c.HotPathExecutor([sub])
    executor.add_node(node)
    spin_thread, box = _spin_in_thread(executor)
    pub = node.create_publisher(String, "/hot_path_test", c.reliable_qos(10))
    assert _wait(lambda: pub.get_subscription_count() >= 1)
    pub.publish(String(data="fine"))
    assert _wait(lambda: seen == ["fine"])
    assert spin_thread.is_alive()
    pub.publish(String(data="boom"))
    spin_thread.join(10.0)
    assert not spin_thread.is_alive(), "the spin did not end"
    assert isinstance(box["error"], RuntimeError) and "failed on 'boom'" in str(box["error"])
    executor.shutdown()
    assert not executor._hot_thread.is_alive()


def test_a_context_shut_down_between_the_spins_look_and_its_wait_ends_the_spin_quietly(ros_env):
    """rclpy's signal thread shuts the context down whenever SIGINT lands: here right after
    ``spin``'s look at the context, before the executor's wait builds its timer (rclpy raises
    RCLError "failed to create timer: the given context is not valid"); the node stopped as asked,
    so the spin ends without an error.  With the context up, the same error is raised."""
    from rclpy.executors import SingleThreadedExecutor

    class ShutAtTheWait(SingleThreadedExecutor):
        def spin_once(self, timeout_sec=None):
            rclpy.shutdown(context=self.context)       # what the signal thread does, at the worst moment
            super().spin_once(timeout_sec=timeout_sec)

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("spin_shut_at_the_wait", context=context)
    c.spin(node, ShutAtTheWait(context=context))      # returns: no RCLError
    assert not context.ok()
    node.destroy_node()

    class FailsWhileUp(SingleThreadedExecutor):
        def spin_once(self, timeout_sec=None):
            raise RuntimeError("an rclpy failure with the context up")

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("spin_fails_while_up", context=context)
    with pytest.raises(RuntimeError, match="context up"):
        c.spin(node, FailsWhileUp(context=context))
    node.destroy_node()
    rclpy.shutdown(context=context)


def test_a_stop_signal_raised_inside_a_finalizer_is_silent_and_ends_the_spin(ros_env, monkeypatch):
    """A KeyboardInterrupt that lands in ``Task.__del__`` cannot be raised there: Python hands it
    to ``sys.unraisablehook``, which printed a traceback and let the node spin on.  A node's hook
    (:func:`executor.install_stop_hook`, every node's ``main``) passes it on to nothing and the
    spin ends, the context still up; any other unraisable exception goes to the hook before it."""
    import sys
    from rclpy.executors import SingleThreadedExecutor
    from inclinometer_calib.nodes import executor as ex

    passed_on = []
    monkeypatch.setattr(sys, "unraisablehook", passed_on.append)   # the hook before (restored after)
    ex.install_stop_hook()
    assert sys.unraisablehook is ex._quiet_interrupted_task and not ex.INTERRUPTED.is_set()

    class InterruptedFinalizer:
        def __del__(self):
            raise KeyboardInterrupt

    class OtherFinalizer:
        def __del__(self):
            raise ValueError("a finalizer's own error")

    class DropsATask(SingleThreadedExecutor):
        turns = 0

        def spin_once(self, timeout_sec=None):
            DropsATask.turns += 1
            if DropsATask.turns > 3:                        # a spin that went on: end it, the test fails
                rclpy.shutdown(context=self.context)
                return
            OtherFinalizer()
            InterruptedFinalizer()                          # collected at once: its __del__ raises
            super().spin_once(timeout_sec=0.0)

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("spin_interrupted_in_a_finalizer", context=context)
    try:
        c.spin(node, DropsATask(context=context))
        assert DropsATask.turns == 1 and context.ok()
        assert [type(u.exc_value) for u in passed_on] == [ValueError]   # the interrupt: not passed on
    finally:
        ex.INTERRUPTED.clear()
        node.destroy_node()
        rclpy.shutdown(context=context)


def test_a_stop_signal_raised_inside_a_finalizer_makes_the_shutdown_wait_for_rclpys_signal_thread(ros):
    """After a Ctrl-C, :meth:`HotPathExecutor.shutdown` lets rclpy's signal thread shut the context
    down before the SIGINT guards can go (freed while that thread walks them: a segfault); a Ctrl-C
    that landed in a finalizer (``INTERRUPTED``) is the same Ctrl-C: the shutdown waits for the
    context, here at most ``signal_wait_s`` since no signal thread is at work."""
    import time as _time
    from rclpy.signals import SignalHandlerOptions, get_current_signal_handlers_options
    from inclinometer_calib.nodes import executor as ex

    # rclpy.init() of the default context (the fixture) installs rclpy's handlers, as in a node
    assert get_current_signal_handlers_options() == SignalHandlerOptions.ALL
    executor = c.HotPathExecutor(signal_wait_s=0.3)
    ex.INTERRUPTED.set()
    try:
        t0 = _time.monotonic()
        executor.shutdown()
        assert _time.monotonic() - t0 >= 0.3          # it waited for the context to go down
    finally:
        ex.INTERRUPTED.clear()


def _two_station_node(ros, tmp_path, with_temperature_effect=False, params=()):
    """A correction node called directly (no executor), its record the simulated probe's (with a
    temperature effect if asked), and the probe's messages of two stations: (node, log, messages)."""
    from inclinometer_calib.core import effects as fx
    from inclinometer_calib.core.model import ProbeModel

    probe = sim.build_probe(3)
    model = ProbeModel.base(probe.acc, probe.mag)
    if with_temperature_effect:
        model = model.with_effect(fx.make_effect("temperature_bias", "mag", "xyz"), "all")
    path = tmp_path / "coeffs.yaml"
    Calibration(model, probe_id="hot", site=Site()).save(path)
    refs = [(30.0, 60.0, 0.0), (40.0, 120.0, 90.0)]
    log = sim.run_session(probe, Site(), [Station.planned(sim.orientation_matrix(*r), 2.0, ref=r) for r in refs],
                          np.random.default_rng(1), rate_hz=100.0, move_s=0.5, survey=True)
    node = CorrectionNode(parameter_overrides=[Parameter("coeffs_file", value=str(path)),
                                               Parameter("use_topic", value=False), *params])
    ros.append(node)
    node.pub_station, node.pub_diag = _Collect(), _Collect()
    return node, log, _messages(log)


def test_a_station_waits_for_the_first_temperature_its_record_needs(ros, tmp_path):
    """A record with a temperature effect, and the temperature topic matched after the samples'
    (its first messages late): the stations closed before the first temperature wait for it, then
    go out corrected with it, not uncorrectable (NaN) at once."""
    node, _, msgs = _two_station_node(ros, tmp_path, with_temperature_effect=True)
    for mi, mm, _ in msgs:                      # the samples, and no temperature yet
        node.stream._on_imu(serialize_message(mi), None)
        node.stream._on_mag(serialize_message(mm))
    node.stream.close_hold()
    assert node.pub_station.msgs == [] and len(node.engine._pending) == 2
    assert [w for _, _, w in node.engine.waiting()] == [["temperature"], ["temperature"]]
    for _, _, mt in msgs:                       # the temperatures, late
        node.stream._on_temp(serialize_message(mt))
    got = node.pub_station.msgs
    assert len(got) == 2 and all(math.isfinite(s.azimuth_deg) and math.isfinite(s.temperature_c) for s in got)


def test_a_station_waits_until_its_readers_are_matched_then_goes_or_says_who_missed_it(ros, tmp_path, capfd):
    """The launcher names the station readers it starts; a reader the probe already sees in the
    graph may not be matched with the correction node's publisher yet (under load the WITS node
    missed the first station): stations wait for the match, and after reference_wait_s go anyway,
    saying how many readers were matched.  (The engine has let them out: they wait in the node's
    outbox, in order, for their readers.)"""
    wait_s = 1.0
    node, _, msgs = _two_station_node(ros, tmp_path, params=[Parameter("wait_for_station_readers", value=2),
                                                             Parameter("reference_wait_s", value=wait_s)])
    node.pub_station.readers = 1                # one reader short: the first station waits
    for mi, mm, mt in msgs:
        node.stream._on_imu(serialize_message(mi), None)
        node.stream._on_mag(serialize_message(mm))
        node.stream._on_temp(serialize_message(mt))
    assert node.pub_station.msgs == [] and len(node._outbox) == 1 and not node.engine._pending
    node.pub_station.readers = 2                # matched: it goes at the next message
    node.stream._on_temp(serialize_message(msgs[-1][2]))
    assert len(node.pub_station.msgs) == 1 and not node._outbox
    node.pub_station.readers = 1                # a reader gone: the last one waits, then goes, said
    node.stream.close_hold()
    assert len(node.pub_station.msgs) == 1 and len(node._outbox) == 1
    node._flush_outbox()                        # the node's outbox timer, before reference_wait_s: it waits
    assert len(node.pub_station.msgs) == 1 and len(node._outbox) == 1
    assert "/survey/station readers matched" not in capfd.readouterr().err
    time.sleep(wait_s + 0.05)
    node._flush_outbox()                        # reference_wait_s is over
    assert len(node.pub_station.msgs) == 2 and not node._outbox
    assert "1 of 2 /survey/station readers matched" in capfd.readouterr().err


def test_an_unstamped_depth_holds_from_the_sample_sent_after_it_however_late_it_is_taken(ros, tmp_path):
    """The probe publishes a depth change just before the first sample at the new depth; the
    correction node places it by the DDS source timestamps, so a depth taken after later samples
    (its reader behind the Imu reader's, a loaded machine) still gives each station its own."""
    from std_msgs.msg import Float64

    node, log, msgs = _two_station_node(ros, tmp_path)
    j = int(np.argmax(log.t_s > log.t_s[0] + 2.25))        # in the move between the stations
    src = [1_000_000 * (k + 1) for k in range(len(msgs))]   # ns, the probe's publish order
    node.stream._on_depth(Float64(data=500.0), {"source_timestamp": 1})
    for k, (mi, mm, mt) in enumerate(msgs):
        node.stream._on_imu(serialize_message(mi), {"source_timestamp": src[k]})
        node.stream._on_mag(serialize_message(mm))
        node.stream._on_temp(serialize_message(mt))
    node.stream._on_depth(Float64(data=530.0), {"source_timestamp": src[j] - 1})   # sent before sample j, taken last
    node.engine.end()                           # the end of the data: what came is all there is
    node.stream._after()
    assert [s.measured_depth_m for s in node.pub_station.msgs] == [500.0, 530.0]
