"""Exposures without ROS: the beam log and the frame rule, and the ExposureGate's threads and deadline."""

import threading
import time

import numpy as np
import pytest

from robot_ct_ros.hardware.detector import DetectorError, Frame
from robot_ct_ros.hardware.exposure import BeamLog, ExposureGate, frame_usable

S = 1_000_000_000


def test_beam_log_fraction_and_state():
    log = BeamLog()
    assert log.fraction(0, 10) == 0.0 and not log.on_at(5)  # off before the first report
    log.record(2, True)
    log.record(3, True)  # not a change: not kept
    log.record(6, False)
    assert log.entries == [(2, True), (6, False)]
    assert log.fraction(0, 10) == pytest.approx(0.4)
    assert log.fraction(3, 5) == 1.0 and log.fraction(6, 9) == 0.0 and log.fraction(5, 5) == 0.0
    assert log.on_at(2) and log.on_at(5) and not log.on_at(6) and not log.on_at(1)


def test_beam_log_keeps_a_minute_and_the_state_before_it():
    log = BeamLog()
    for i in range(10):
        log.record(i * 30 * S, i % 2 == 0)
    # at 270 s: everything since 210 s, and the entry before it (the state at 210 s - 0)
    assert log.entries == [(180 * S, True), (210 * S, False), (240 * S, True), (270 * S, False)]
    assert log.fraction(190 * S, 200 * S) == 1.0


@pytest.mark.parametrize("fraction, on_at_request, usable", [
    (1.0, True, True), (1.0, False, True),    # a projection (the beam came on just before the exposure)
    (0.0, False, True),                       # a dark frame
    (0.0, True, False),                       # dropped before the exposure started: not a clean dark frame
    (0.5, True, False), (0.5, False, False),  # interrupted
])
def test_frame_usable(fraction, on_at_request, usable):
    assert frame_usable(fraction, on_at_request) is usable


class FakeDetector:
    """acquire() returns a frame after ``delay_s``, raises ``error``, or hangs until released."""

    def __init__(self, delay_s=0.01, error=None, hang=False):
        self.delay_s, self.error, self.hang = delay_s, error, hang
        self.is_connected = True
        self.release = threading.Event()
        self.calls = 0

    def acquire(self, exposure_s):
        self.calls += 1
        if self.hang:
            self.release.wait(5.0)
        time.sleep(self.delay_s)
        if self.error is not None:
            raise self.error
        return Frame(np.zeros((2, 3), np.float32), 10, 20)


def _gate(**kw):
    gate = ExposureGate(time.monotonic_ns, **kw)
    gate.activate()
    return gate


def test_gate_delivers_the_frame():
    gate = _gate()
    result = gate.expose(FakeDetector(), 0.01, 1.0)
    assert result.frame is not None and result.frame.stamp_ns == 15 and not result.problem and not result.fault
    assert result.requested_ns > 0 and gate.pending is None


def test_gate_refusals_are_faults_only_when_the_detector_is_at_fault():
    gate = ExposureGate(time.monotonic_ns)
    r = gate.expose(FakeDetector(), 0.01, 1.0, state="inactive")
    assert r.frame is None and r.problem == "detector not active (lifecycle state inactive)" and not r.fault
    gate.activate()
    r = gate.expose(None, 0.01, 1.0)
    assert r.problem == "detector not connected" and r.fault == "exposure refused: detector not connected"
    det = FakeDetector(delay_s=0.3)
    t = threading.Thread(target=gate.expose, args=(det, 0.01, 1.0))
    t.start()
    assert _until(lambda: gate.pending is not None)
    r = gate.expose(det, 0.01, 1.0)
    assert "busy" in r.problem and not r.fault
    t.join()


def _until(predicate, timeout_s=5.0):
    end = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < end:
        time.sleep(0.002)
    return predicate()


def test_gate_deadline_and_a_hung_detector():
    late = []
    gate = _gate(on_late_frame=lambda: late.append(True))
    det = FakeDetector(hang=True)
    t0 = time.monotonic()
    r = gate.expose(det, 0.01, 0.2)
    assert time.monotonic() - t0 < 1.0
    assert r.frame is None and r.problem == "detector timeout: no frame within 0.2 s" and r.fault.startswith(
        "exposure failed: detector timeout")
    r = gate.expose(det, 0.01, 0.2)  # the acquisition still hangs: the detector does not respond
    assert "not responding" in r.problem and r.fault and det.calls == 1
    det.release.set()
    gate.join(2.0)
    assert late == [True]  # the late frame was dropped, and said so
    assert gate.expose(det, 0.01, 1.0).frame is not None


def test_gate_reports_driver_errors_and_cancellation():
    gate = _gate()
    r = gate.expose(FakeDetector(error=DetectorError("read-out failed")), 0.01, 1.0)
    assert r.problem == "DetectorError: read-out failed"
    assert r.fault == "exposure failed: DetectorError: read-out failed"
    det = FakeDetector(delay_s=0.5)
    results = []
    t = threading.Thread(target=lambda: results.append(gate.expose(det, 0.01, 5.0)))
    t.start()
    assert _until(lambda: gate.pending is not None)
    gate.cancel("deactivated during the exposure")
    t.join(2.0)
    assert results[0].frame is None and results[0].problem == "deactivated during the exposure"
    assert not results[0].fault and not gate.active
    assert "not active" in gate.expose(det, 0.01, 1.0).problem
