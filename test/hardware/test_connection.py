"""BackgroundConnection without ROS: results handed over once, failures reported, abandoned attempts cleaned up."""

import threading

from robot_ct_ros.hardware.arm import ArmConnectionError
from robot_ct_ros.hardware.connection import BackgroundConnection, quiet_disconnect
from robot_ct_ros.testing import wait_until


def _wait(predicate):
    return wait_until(predicate, timeout_s=5.0)


class FakeArm:
    """connect() raises ``error`` or, with ``hold``, waits until it is set; records the disconnecting thread."""

    def __init__(self, error=None, hold=None, disconnect_error=None):
        self.error, self.hold, self.disconnect_error = error, hold, disconnect_error
        self.connected = False
        self.connect_threads, self.disconnect_threads = [], []

    def connect(self):
        self.connect_threads.append(threading.current_thread())
        if self.hold is not None:
            assert self.hold.wait(5.0)
        if self.error is not None:
            raise self.error
        self.connected = True

    def disconnect(self):
        self.disconnect_threads.append(threading.current_thread())
        self.connected = False
        if self.disconnect_error is not None:
            raise self.disconnect_error


class Notified:
    def __init__(self):
        self.count = 0
        self.event = threading.Event()

    def __call__(self):
        self.count += 1
        self.event.set()


def test_a_connection_is_made_off_the_callers_thread_and_handed_over_once():
    notify = Notified()
    conn = BackgroundConnection(notify, name="source_arm")
    arm = FakeArm()
    assert conn.take() is None and not conn.connecting
    t = conn.start(arm)
    assert conn.connecting and t.name == "source_arm_connect"
    assert notify.event.wait(5.0) and notify.count == 1
    assert arm.connect_threads == [t] and t is not threading.current_thread()
    assert conn.connecting  # until the caller takes the result
    assert conn.arm is None and conn.take() == (arm, None)
    assert not conn.connecting and conn.take() is None  # once
    assert arm.connected and not arm.disconnect_threads and conn.arm is arm
    assert conn.elapsed_s >= 0.0
    conn.disconnect()  # let go of on a thread of its own
    assert conn.arm is None
    conn.close(5.0)
    assert len(arm.disconnect_threads) == 1 and arm.disconnect_threads[0] is not threading.current_thread()
    assert arm.disconnect_threads[0].name == "source_arm_disconnect" and not arm.connected


def test_a_connect_that_raises_is_reported_not_lost():
    for exc, reported in ((ArmConnectionError("10.0.0.9: no answer"), "10.0.0.9: no answer"),
                          (OSError("unreachable"), "unreachable"),
                          (ZeroDivisionError("a driver bug"), "ZeroDivisionError: a driver bug")):
        notify = Notified()
        conn = BackgroundConnection(notify)
        arm = FakeArm(error=exc)
        conn.start(arm)
        assert notify.event.wait(5.0)
        assert conn.take() == (arm, reported)
        assert not conn.connecting and not arm.disconnect_threads and conn.arm is None


def test_a_hung_attempt_abandoned_then_succeeding_is_disconnected_on_its_own_thread():
    notify = Notified()
    conn = BackgroundConnection(notify)
    hold = threading.Event()
    arm = FakeArm(hold=hold)
    t = conn.start(arm)
    assert _wait(lambda: arm.connect_threads)
    conn.abandon()
    assert not conn.connecting
    hold.set()  # the controller answers at last
    t.join(5.0)
    assert not t.is_alive()
    assert arm.disconnect_threads == [t] and not arm.connected  # let go of there, not on the caller's thread
    assert notify.count == 0 and conn.take() is None and conn.arm is None
    # disconnect() while connecting abandons the attempt the same way
    hold2 = threading.Event()
    arm2 = FakeArm(hold=hold2)
    t2 = conn.start(arm2)
    assert _wait(lambda: arm2.connect_threads)
    conn.disconnect()
    assert not conn.connecting
    hold2.set()
    t2.join(5.0)
    assert arm2.disconnect_threads == [t2] and conn.take() is None and conn.arm is None


def test_a_stale_result_of_an_older_attempt_is_discarded():
    notify = Notified()
    conn = BackgroundConnection(notify)
    hold = threading.Event()
    old, new = FakeArm(hold=hold), FakeArm()
    t_old = conn.start(old)
    assert _wait(lambda: old.connect_threads)
    conn.start(new)  # supersedes the hung attempt
    assert notify.event.wait(5.0)
    notify.event.clear()
    hold.set()
    t_old.join(5.0)
    assert old.disconnect_threads == [t_old] and not old.connected
    assert notify.count == 1  # only the current attempt notifies
    assert conn.take() == (new, None) and new.connected and not new.disconnect_threads
    # a failed older attempt is dropped silently too
    hold2 = threading.Event()
    failing = FakeArm(error=OSError("late"), hold=hold2)
    t = conn.start(failing)
    assert _wait(lambda: failing.connect_threads)
    conn.abandon()
    hold2.set()
    t.join(5.0)
    assert conn.take() is None and notify.count == 1 and not failing.disconnect_threads


def test_a_result_ready_but_abandoned_before_it_is_taken_is_not_handed_over():
    notify = Notified()
    conn = BackgroundConnection(notify)
    conn.start(FakeArm())
    assert notify.event.wait(5.0)
    conn.abandon()
    assert conn.take() is None and not conn.connecting
    # ready, not yet taken, and a new attempt starts: the older result is not the new attempt's
    notify.event.clear()
    conn.start(FakeArm())
    assert notify.event.wait(5.0)
    hold = threading.Event()
    hung = FakeArm(hold=hold)
    conn.start(hung)
    assert conn.take() is None and conn.connecting
    hold.set()
    assert _wait(lambda: hung.connected)
    assert _wait(lambda: conn.take() == (hung, None))


def test_a_notify_that_raises_lets_go_of_the_arm():
    def gone():
        raise RuntimeError("guard condition destroyed")

    conn = BackgroundConnection(gone)
    arm = FakeArm()
    t = conn.start(arm)
    t.join(5.0)
    assert arm.disconnect_threads == [t] and not arm.connected


def test_release_disconnects_on_a_thread_and_close_waits_for_it():
    warnings = []
    conn = BackgroundConnection(lambda: None, warnings.append, name="detector_arm")
    hold = threading.Event()

    class SlowArm(FakeArm):
        def disconnect(self):
            assert hold.wait(5.0)
            super().disconnect()

    slow, bad = SlowArm(), FakeArm(disconnect_error=OSError("socket closed"))
    conn.release(slow)
    conn.release(bad)
    assert _wait(lambda: bad.disconnect_threads) and bad.disconnect_threads[0] is not threading.current_thread()
    assert bad.disconnect_threads[0].name == "detector_arm_disconnect"
    assert _wait(lambda: warnings == ["disconnect: socket closed"])
    assert not slow.disconnect_threads  # still waiting: release returned at once
    threading.Timer(0.1, hold.set).start()
    conn.close(5.0)
    assert slow.disconnect_threads and not slow.connected


def test_quiet_disconnect_never_raises():
    quiet_disconnect(FakeArm(disconnect_error=RuntimeError("boom")))
    said = []
    quiet_disconnect(FakeArm(disconnect_error=RuntimeError("boom")), said.append)
    assert said == ["disconnect: boom"]
