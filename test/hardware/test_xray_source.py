"""The beam interlock: each condition alone keeps the beam off."""

import pytest

from robot_ct_ros.hardware.xray_source import (InterlockedSource, SimulatedXraySource, SourceError, SourceSettings,
                                               beam_permitted, InterlockInputs)

ALL_OK = dict(scan_armed=True, source_arm_in_position=True, detector_arm_in_position=True,
              source_arm_stamp_s=10.0, detector_arm_stamp_s=10.0, estop_latched=False)


def test_all_conditions_met_permits_beam():
    assert beam_permitted(InterlockInputs(**ALL_OK), now_s=10.5, max_report_age_s=1.0)[0]


@pytest.mark.parametrize("change, reason", [
    (dict(scan_armed=False), "not armed"),
    (dict(source_arm_in_position=False), "source arm not in position"),
    (dict(detector_arm_in_position=False), "detector arm not in position"),
    (dict(estop_latched=True), "e-stop"),
    (dict(source_arm_stamp_s=8.0), "source arm report stale"),
    (dict(detector_arm_stamp_s=8.0), "detector arm report stale"),
])
def test_each_condition_alone_refuses_and_cuts_beam(change, reason):
    ok, why = beam_permitted(InterlockInputs(**{**ALL_OK, **change}), now_s=10.5, max_report_age_s=1.0)
    assert not ok and reason in why

    src = InterlockedSource(SimulatedXraySource(), max_report_age_s=1.0)
    src.update(10.0, **ALL_OK)
    assert src.request_beam(True, 10.1)[0] and src.beam_on
    src.update(10.5, **change)
    assert not src.beam_on
    assert not src.request_beam(True, 10.6)[0]


def test_stale_reports_cut_beam_on_tick():
    src = InterlockedSource(SimulatedXraySource(), max_report_age_s=0.5)
    src.update(0.0, scan_armed=True)
    src.report_arm("source", True, 0.0)
    src.report_arm("detector", True, 0.0)
    assert src.request_beam(True, 0.1)[0]
    src.tick(0.4)
    assert src.beam_on
    src.tick(0.6)
    assert not src.beam_on
    assert src.source.beam_on_seconds == pytest.approx(0.5)


def test_source_limits():
    s = SimulatedXraySource()
    with pytest.raises(SourceError):
        s.configure(200.0, 100.0)
    with pytest.raises(SourceError):
        s.configure(90.0, 500.0)
    s.set_beam(True, 0.0)
    with pytest.raises(SourceError):
        s.configure(80.0, 100.0)


def test_settings_configure_the_source_behind_the_interlock():
    interlock = SourceSettings(kvp=80.0, power_w=100.0, max_report_age_s=0.5).interlocked(SimulatedXraySource())
    assert isinstance(interlock, InterlockedSource) and interlock.max_report_age_s == 0.5
    assert (interlock.source.kvp, interlock.source.power_w) == (80.0, 100.0) and not interlock.beam_on
    with pytest.raises(SourceError, match="kVp 200"):  # the source's range, not the settings', decides
        SourceSettings(kvp=200.0).interlocked(SimulatedXraySource())
    with pytest.raises(ValueError, match="max_report_age_s must be >= 0"):
        SourceSettings(max_report_age_s=-1.0)


def test_a_beam_left_on_is_cut_after_max_beam_on_s():
    """An orchestrator that dies with the beam on (armed, arms in position and reporting) once left it on for good:
    the interlock cuts it after max_beam_on_s, says why, and a new exposure may switch it on again."""
    src = SourceSettings(max_beam_on_s=2.0).interlocked(SimulatedXraySource())
    src.update(0.0, scan_armed=True)
    for t in (0.0, 0.5, 1.0, 1.5, 2.0, 2.5):
        src.report_arm("source", True, t)
        src.report_arm("detector", True, t)
        src.tick(t)
        if t == 0.0:
            assert src.request_beam(True, 0.0)[0]
        assert src.beam_on == (t <= 2.0), t
    assert "longer than max_beam_on_s 2 s" in src.last_cut_reason
    assert src.source.total_beam_on_s(2.5) == pytest.approx(2.5)
    assert src.request_beam(True, 2.5)[0] and src.source.total_beam_on_s(3.0) == pytest.approx(3.0)


def test_after_an_estop_the_scan_must_be_armed_anew():
    """Arming while the e-stop is latched is ignored, so a reset does not bring the beam back by itself."""
    src = InterlockedSource(SimulatedXraySource(), max_report_age_s=1.0)
    src.update(10.0, **ALL_OK)
    assert src.request_beam(True, 10.1)[0]
    src.estop(10.2)
    assert not src.beam_on and not src.inputs.scan_armed
    src.update(10.3, scan_armed=True)  # someone arms during the latch
    assert not src.inputs.scan_armed
    src.reset_estop(10.4)
    ok, why = src.request_beam(True, 10.5)
    assert not ok and "not armed" in why
    src.update(10.6, scan_armed=True)
    assert src.request_beam(True, 10.7)[0]


def test_a_driver_fault_is_an_answer_not_an_exception():
    """SourceError from the driver once escaped request_beam and the tick (the node's callbacks crashed and a
    refused switch-off was never retried): now a refused switch-on is a refusal naming the fault, a refused
    switch-off is retried on every tick, and the fault stays until the refused command succeeds."""
    src = InterlockedSource(SimulatedXraySource(), max_report_age_s=1.0)
    src.update(10.0, **ALL_OK)
    src.source.fault_on = SourceError("tube arc detected")
    ok, why = src.request_beam(True, 10.1)
    assert not ok and "beam refused: source refused beam on: tube arc detected" == why and not src.beam_on
    assert "tube arc" in src.fault
    assert src.request_beam(False, 10.15)[0] and "tube arc" in src.fault  # switching off does not clear it
    src.source.fault_on = None
    assert src.request_beam(True, 10.2)[0] and src.fault == ""

    src.source.fault_off = SourceError("shutter did not confirm closed")
    src.update(10.3, scan_armed=False)
    assert src.beam_on and "shutter did not confirm closed" in src.fault and src.last_cut_reason == ""
    ok, why = src.request_beam(False, 10.35)
    assert not ok and "shutter" in why
    tries = src.source.off_tries
    src.tick(10.4)
    src.tick(10.5)
    assert src.source.off_tries == tries + 2 and src.beam_on  # retried on every tick
    src.source.fault_off = None
    src.tick(10.6)
    assert not src.beam_on and src.fault == "" and "not armed" in src.last_cut_reason


def test_the_max_beam_on_cut_is_remembered_until_a_new_scan_or_exposure():
    """The watchdog's cut left nothing to report (/diagnostics stayed OK): it is kept until a scan is armed anew
    or the beam is switched on again; an ordinary cut (disarmed) is not a watchdog cut."""
    src = SourceSettings(max_beam_on_s=1.0).interlocked(SimulatedXraySource())
    src.update(0.0, **{**ALL_OK, "source_arm_stamp_s": 0.0, "detector_arm_stamp_s": 0.0})
    assert src.request_beam(True, 0.0)[0]
    for t in (0.5, 1.2):
        src.report_arm("source", True, t)
        src.report_arm("detector", True, t)
        src.tick(t)
    assert not src.beam_on and src.watchdog_cut.startswith("beam cut: beam on for 1.2 s, longer than max_beam_on_s")
    src.tick(1.3)
    assert src.watchdog_cut  # kept
    assert src.request_beam(True, 1.4)[0] and src.watchdog_cut == ""  # a good exposure
    src.update(1.5, scan_armed=False)
    assert not src.beam_on and src.watchdog_cut == ""  # not the watchdog
    src._on_since, src.watchdog_cut = None, "beam cut: x"
    src.update(1.6, scan_armed=True)  # a new scan
    assert src.watchdog_cut == ""


def test_a_refused_switch_off_is_retried_while_the_interlock_still_permits_the_beam():
    """A switch-off asked for and refused was retried only when the interlock itself forbade the beam: with the scan
    armed and both arms in position the beam stayed on for good. Now it is retried on every tick until it succeeds;
    a switch-on request refused by the interlock does not cancel it, one that is permitted and succeeds does."""
    src = InterlockedSource(SimulatedXraySource(), max_report_age_s=1.0)
    src.update(10.0, **ALL_OK)
    assert src.request_beam(True, 10.1)[0]
    src.source.fault_off = SourceError("shutter did not confirm closed")
    ok, why = src.request_beam(False, 10.2)
    assert not ok and "shutter" in why and src.beam_on
    tries = src.source.off_tries
    src.tick(10.3)
    src.tick(10.4)
    assert src.source.off_tries == tries + 2 and src.beam_on and src.off_pending  # retried on every tick
    src.source.fault_off = None
    src.tick(10.5)
    assert not src.beam_on and not src.off_pending and src.fault == ""

    assert src.request_beam(True, 10.6)[0]
    src.source.fault_off = SourceError("shutter did not confirm closed")
    assert not src.request_beam(False, 10.7)[0]
    src.update(10.75, scan_armed=False)
    assert not src.request_beam(True, 10.8)[0] and src.off_pending  # not permitted: the switch-off stays pending
    src.update(10.85, scan_armed=True)
    assert src.request_beam(True, 10.9)[0] and not src.off_pending  # a permitted, successful switch-on supersedes it
    tries = src.source.off_tries
    src.tick(11.0)
    assert src.beam_on and src.source.off_tries == tries


@pytest.mark.parametrize("error", [OSError("serial port gone"), TimeoutError("no answer in 0.5 s"),
                                   RuntimeError("socket closed")])
def test_any_driver_exception_is_a_fault_and_a_refused_switch_off_is_retried(error):
    """Only SourceError was caught: an OSError from a serial driver escaped request_beam and the tick (the node's
    executor ended with the beam on). Now any exception is a fault named with its type, never raised."""
    src = InterlockedSource(SimulatedXraySource(), max_report_age_s=1.0)
    src.update(10.0, **ALL_OK)
    src.source.fault_on = src.source.fault_off = error
    ok, why = src.request_beam(True, 10.1)
    name = type(error).__name__
    assert not ok and why == f"beam refused: source refused beam on: {name}: {error}" and not src.beam_on
    src.source.fault_on = src.source.fault_off = None
    assert src.request_beam(True, 10.2)[0] and src.fault == ""
    src.source.fault_on = src.source.fault_off = error
    ok, why = src.request_beam(False, 10.3)
    assert not ok and f"source refused beam off: {name}" in why and src.beam_on
    src.update(10.4, scan_armed=False)  # the interlock's cut is refused too, and does not raise
    src.tick(10.5)
    assert src.beam_on and f"{name}: {error}" in src.fault
    src.source.fault_on = src.source.fault_off = None
    src.tick(10.6)
    assert not src.beam_on and src.fault == "" and not src.off_pending


def test_a_refused_switch_off_is_retried_at_the_tick_rate_not_on_every_arm_report():
    """Every input change retried a refused switch-off: two arms reporting at 50 Hz asked a refusing driver about
    110 times a second, and a driver whose refusal takes 50 ms held the node's only executor thread most of the time.
    Now arm reports and other input changes do not retry it (the first cut they cause still tries at once); each
    tick does, and an e-stop does at once."""
    src = InterlockedSource(SimulatedXraySource(), max_report_age_s=1.0)
    src.update(10.0, **ALL_OK)
    assert src.request_beam(True, 10.01)[0]
    src.source.fault_off = SourceError("HV controller busy")
    tries = src.source.off_tries
    src.report_arm("detector", False, 10.02)  # the interlock's cut: tried at once, refused
    assert src.source.off_tries == tries + 1 and src.beam_on and src.off_pending
    for k in range(10):  # arm reports between two ticks
        src.report_arm("source", True, 10.03 + 0.002 * k)
        src.report_arm("detector", k % 2 == 0, 10.03 + 0.002 * k)
    src.update(10.06, scan_armed=False)
    assert src.source.off_tries == tries + 1
    src.tick(10.1)
    assert src.source.off_tries == tries + 2
    src.estop(10.12)
    assert src.source.off_tries == tries + 3 and src.beam_on
    src.source.fault_off = None
    src.tick(10.2)
    assert not src.beam_on and not src.off_pending and src.source.off_tries == tries + 4
