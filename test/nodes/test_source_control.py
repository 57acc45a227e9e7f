"""source_control in-process: the beam follows the interlock and the lifecycle over real topics and services."""

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from std_msgs.msg import Bool
from std_srvs.srv import SetBool, Trigger

from robot_ct_ros.hardware.xray_source import SimulatedXraySource, SourceError
from robot_ct_ros.nodes.source_control import LATCHED, SourceControlNode


INTERLOCK_INPUTS = ("scan/armed", "source_arm/in_position", "detector_arm/in_position")


def _probe(ros, inputs=INTERLOCK_INPUTS):
    """A probe node wired to the source: (probe, publishers of ``inputs``, beam states received, set_beam client)."""
    probe = ros.node("probe")
    beam = []
    sub = probe.create_subscription(Bool, "source/beam_on", lambda m: beam.append(m.data), LATCHED)
    pubs = {name: probe.create_publisher(Bool, name, 10) for name in inputs}
    for pub in pubs.values():
        assert ros.wait_for_subscribers(pub)
    assert ros.wait_for_publishers(sub)
    return probe, pubs, beam, probe.create_client(SetBool, "source/set_beam")


def _setup(ros):
    node = ros.add(SourceControlNode(context=ros.context))
    probe, pubs, beam, set_beam = _probe(ros, INTERLOCK_INPUTS + ("estop",))
    return node, probe, pubs, beam, set_beam


def _ready(ros, pubs, node):
    for name in ("scan/armed", "source_arm/in_position", "detector_arm/in_position"):
        pubs[name].publish(Bool(data=True))
    assert ros.spin_until(lambda: node.interlock.inputs.detector_arm_in_position
                          and node.interlock.inputs.scan_armed and node.interlock.inputs.source_arm_in_position)


def test_smoke_publish_and_receive(ros):
    """A node starts in-process, receives a message and publishes one."""
    node, probe, pubs, beam, _ = _setup(ros)
    assert ros.spin_until(lambda: len(beam) > 0)  # latched initial state arrives
    assert beam[-1] is False
    pubs["scan/armed"].publish(Bool(data=True))
    assert ros.spin_until(lambda: node.interlock.inputs.scan_armed)


def test_beam_refused_until_interlock_satisfied_then_cut_by_estop(ros):
    node, probe, pubs, beam, set_beam = _setup(ros)
    answer = ros.call(set_beam, SetBool.Request(data=True))
    assert not answer.success and "not armed" in answer.message
    assert not node.interlock.beam_on

    _ready(ros, pubs, node)
    answer = ros.call(set_beam, SetBool.Request(data=True))
    assert answer.success, answer.message
    assert ros.spin_until(lambda: beam and beam[-1] is True)

    pubs["estop"].publish(Bool(data=True))
    assert ros.spin_until(lambda: beam and beam[-1] is False)
    assert node.interlock.inputs.estop_latched
    # latched: arming is ignored, and the beam stays refused
    pubs["scan/armed"].publish(Bool(data=True))
    ros.spin_for(0.3)
    assert not node.interlock.inputs.scan_armed
    assert not ros.call(set_beam, SetBool.Request(data=True)).success
    reset = probe.create_client(Trigger, "source/reset_estop")
    answer = ros.call(reset, Trigger.Request())
    assert answer.success and "re-armed" in answer.message
    # the reset does not re-arm (arming during the latch was ignored): the scan must be armed anew
    answer = ros.call(set_beam, SetBool.Request(data=True))
    assert not answer.success and "not armed" in answer.message
    _ready(ros, pubs, node)
    assert ros.call(set_beam, SetBool.Request(data=True)).success


def test_the_estop_latch_is_published_for_the_orchestrator(ros):
    node, probe, pubs, beam, set_beam = _setup(ros)
    latched = []
    probe.create_subscription(Bool, "source/estop_latched", lambda m: latched.append(m.data), LATCHED)
    assert ros.spin_until(lambda: latched and latched[-1] is False)  # transient-local: a late subscriber hears it
    assert ros.call(probe.create_client(Trigger, "source/estop"), Trigger.Request()).success
    assert ros.spin_until(lambda: latched[-1] is True)
    assert ros.call(probe.create_client(Trigger, "source/reset_estop"), Trigger.Request()).success
    assert ros.spin_until(lambda: latched[-1] is False)


def test_arm_leaving_position_cuts_beam(ros):
    node, probe, pubs, beam, set_beam = _setup(ros)
    _ready(ros, pubs, node)
    assert ros.call(set_beam, SetBool.Request(data=True)).success
    pubs["detector_arm/in_position"].publish(Bool(data=False))
    assert ros.spin_until(lambda: not node.interlock.beam_on)
    assert ros.spin_until(lambda: beam and beam[-1] is False)


def _transition(ros, client, transition_id):
    return ros.call(client, ChangeState.Request(transition=Transition(id=transition_id))).success


def test_lifecycle_beam_only_while_active(ros):
    """Configure builds the source, activate serves the beam, deactivate/shutdown switch it off at once."""
    node = ros.add(SourceControlNode(context=ros.context, parameter_overrides=[Parameter("autostart", value=False)]))
    probe, pubs, beam, set_beam = _probe(ros)
    change = probe.create_client(ChangeState, "/source_control/change_state")
    get = probe.create_client(GetState, "/source_control/get_state")

    assert ros.call(get, GetState.Request()).current_state.label == "unconfigured"
    assert node.interlock is None
    answer = ros.call(set_beam, SetBool.Request(data=True))
    assert not answer.success and "unconfigured" in answer.message

    assert _transition(ros, change, Transition.TRANSITION_CONFIGURE)
    assert node.lifecycle_state == "inactive" and node.interlock is not None
    _ready(ros, pubs, node)  # every interlock condition met: only the lifecycle state refuses
    answer = ros.call(set_beam, SetBool.Request(data=True))
    assert not answer.success and "inactive" in answer.message and not node.beam_on

    assert _transition(ros, change, Transition.TRANSITION_ACTIVATE)
    _ready(ros, pubs, node)
    assert ros.call(set_beam, SetBool.Request(data=True)).success
    assert ros.spin_until(lambda: beam and beam[-1] is True)

    assert _transition(ros, change, Transition.TRANSITION_DEACTIVATE)
    assert not node.beam_on and not node.interlock.source.beam_on  # off when the transition answers
    assert ros.spin_until(lambda: beam and beam[-1] is False)
    _ready(ros, pubs, node)
    answer = ros.call(set_beam, SetBool.Request(data=True))
    assert not answer.success and "inactive" in answer.message
    ros.spin_for(0.3)  # three interlock ticks: still off
    assert not node.beam_on and beam[-1] is False

    # re-activated: the beam stays off until requested again
    assert _transition(ros, change, Transition.TRANSITION_ACTIVATE)
    assert not node.beam_on
    _ready(ros, pubs, node)
    assert ros.call(set_beam, SetBool.Request(data=True)).success and node.beam_on
    source = node.interlock.source
    assert _transition(ros, change, Transition.TRANSITION_ACTIVE_SHUTDOWN)
    assert not source.beam_on and node.interlock is None and node.lifecycle_state == "finalized"
    assert ros.spin_until(lambda: beam and beam[-1] is False)


def test_estop_latches_in_every_state(ros):
    node = ros.add(SourceControlNode(context=ros.context, parameter_overrides=[Parameter("autostart", value=False)]))
    probe = ros.node("probe")
    estop = probe.create_client(Trigger, "source/estop")
    assert ros.call(estop, Trigger.Request()).success  # unconfigured: no source yet, the latch is kept
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    assert node.interlock.inputs.estop_latched
    pubs = {name: probe.create_publisher(Bool, name, 10)
            for name in ("scan/armed", "source_arm/in_position", "detector_arm/in_position")}
    for pub in pubs.values():
        assert ros.wait_for_subscribers(pub)
    for pub in pubs.values():
        pub.publish(Bool(data=True))
    assert ros.spin_until(lambda: node.interlock.inputs.detector_arm_in_position)
    set_beam = probe.create_client(SetBool, "source/set_beam")
    answer = ros.call(set_beam, SetBool.Request(data=True))
    assert not answer.success and "e-stop" in answer.message
    reset = probe.create_client(Trigger, "source/reset_estop")
    assert ros.call(reset, Trigger.Request()).success
    assert not node.interlock.inputs.estop_latched


def test_bad_source_parameters_fail_configure(ros):
    """Without autostart the configure transition fails (a lifecycle manager sees it); with it, the node ends at
    start as for any bad parameter (it stayed unconfigured for good: its parameters are read-only)."""
    import pytest

    node = ros.add(SourceControlNode(context=ros.context, parameter_overrides=[Parameter("kvp", value=200.0),
                                                                                Parameter("autostart", value=False)]))
    assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
    assert node.lifecycle_state == "unconfigured" and node.interlock is None and "kVp" in node.last_error
    with pytest.raises(ValueError, match="kVp 200.0 outside"):
        SourceControlNode(context=ros.context, parameter_overrides=[Parameter("kvp", value=200.0)])


def test_bad_parameter_values_are_refused_with_a_clear_error(ros):
    import pytest

    for params, words in (({"max_report_age_s": -1.0}, ("parameter max_report_age_s", "out of range")),
                          ({"kvp": "high"}, ("parameter kvp", "DOUBLE"))):
        with pytest.raises(ValueError) as err:
            SourceControlNode(context=ros.context,
                              parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        assert "\n" not in str(err.value) and all(w in str(err.value) for w in words), str(err.value)


def test_a_transition_the_state_does_not_have_is_refused_and_the_node_lives_on(ros):
    """A change_state request by id for a transition the current state lacks (activate while unconfigured,
    configure while active) answers success False; rclpy 7.1.6 alone let the state machine's error end the
    node (rclpy issue 1209)."""
    node = ros.add(SourceControlNode(context=ros.context, parameter_overrides=[Parameter("autostart", value=False)]))
    probe = ros.node("probe")
    change = probe.create_client(ChangeState, "/source_control/change_state")
    get = probe.create_client(GetState, "/source_control/get_state")
    assert not _transition(ros, change, Transition.TRANSITION_ACTIVATE)
    assert ros.call(get, GetState.Request()).current_state.label == "unconfigured"
    assert _transition(ros, change, Transition.TRANSITION_CONFIGURE)
    assert _transition(ros, change, Transition.TRANSITION_ACTIVATE)
    assert not _transition(ros, change, Transition.TRANSITION_CONFIGURE)
    assert ros.call(get, GetState.Request()).current_state.label == "active" and node.interlock is not None
    # by label, rclpy's own refusal
    answer = ros.call(change, ChangeState.Request(transition=Transition(label="configure")))
    assert not answer.success and node.lifecycle_state == "active"


def test_parameters_are_read_only_while_the_node_runs(ros):
    """A running node refuses a parameter change with a reason instead of reporting a value it does not use
    (max_beam_on_s: a shorter limit set at run time would have looked applied and was not)."""
    from rcl_interfaces.srv import GetParameters, SetParameters

    node = ros.add(SourceControlNode(context=ros.context))
    probe = ros.node("probe")
    set_params = probe.create_client(SetParameters, "/source_control/set_parameters")
    for name, value in (("max_beam_on_s", 1.0), ("kvp", 100.0)):
        answer = ros.call(set_params, SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()]))
        assert not answer.results[0].successful and "read-only" in answer.results[0].reason, answer.results[0]
    got = ros.call(probe.create_client(GetParameters, "/source_control/get_parameters"),
                   GetParameters.Request(names=["max_beam_on_s", "kvp"]))
    assert [v.double_value for v in got.values] == [node.settings.max_beam_on_s, node.settings.kvp]


def test_a_whole_number_sets_a_double_parameter(ros):
    """``-p kvp:=90`` is an integer to ROS; rclpy alone refuses it for a double parameter."""
    import pytest
    from rclpy.parameter import Parameter as P

    node = ros.add(SourceControlNode(context=ros.context, parameter_overrides=[
        P("kvp", value=90), P("autostart", value=False)]))
    kvp = node.get_parameter("kvp")
    assert kvp.type_ == P.Type.DOUBLE and kvp.value == 90.0
    with pytest.raises(ValueError, match="parameter kvp"):  # still typed: text is refused
        SourceControlNode(context=ros.context, parameter_overrides=[P("kvp", value="90")])


def test_a_source_driver_fault_is_answered_reported_and_the_node_lives_on(ros):
    """A driver's SourceError once escaped the service and the 10 Hz tick (the executor raised, a refused
    switch-off left beam_on true with nothing reported, destroy_node raised): now set_beam answers no with the
    fault, /diagnostics is ERROR naming it, the switch-off is retried on every tick, and destroy_node logs."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    node = ros.add(SourceControlNode(context=ros.context, source_factory=SimulatedXraySource))
    probe = ros.node("probe")
    diag = []
    probe.create_subscription(DiagnosticArray, "/diagnostics",
                              lambda m: diag.extend(s for s in m.status if s.name.endswith("x-ray source")), 10)
    pubs = {name: probe.create_publisher(Bool, name, 10)
            for name in ("scan/armed", "source_arm/in_position", "detector_arm/in_position")}
    for pub in pubs.values():
        assert ros.wait_for_subscribers(pub)
    set_beam = probe.create_client(SetBool, "source/set_beam")
    _ready(ros, pubs, node)
    source = node.interlock.source

    source.fault_on = SourceError("tube arc detected")
    answer = ros.call(set_beam, SetBool.Request(data=True))
    assert not answer.success and "tube arc detected" in answer.message and not node.beam_on
    assert ros.spin_until(lambda: diag and diag[-1].level == DiagnosticStatus.ERROR
                          and "tube arc detected" in diag[-1].message)
    assert node.lifecycle_state == "active"

    source.fault_on = None
    _ready(ros, pubs, node)
    assert ros.call(set_beam, SetBool.Request(data=True)).success and node.beam_on
    source.fault_off = SourceError("shutter did not confirm closed")
    pubs["scan/armed"].publish(Bool(data=False))
    assert ros.spin_until(lambda: not node.interlock.inputs.scan_armed)
    tries = source.off_tries
    assert ros.spin_until(lambda: source.off_tries >= tries + 3)  # the tick retries
    assert node.beam_on
    assert ros.spin_until(lambda: diag[-1].level == DiagnosticStatus.ERROR and "shutter" in diag[-1].message)
    answer = ros.call(set_beam, SetBool.Request(data=False))
    assert not answer.success and "shutter" in answer.message
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS and node.beam_on
    assert node.trigger_cleanup() != TransitionCallbackReturn.SUCCESS  # the source is kept while the beam is on
    assert node.lifecycle_state == "inactive" and node.interlock is not None
    ros.executor.remove_node(node)
    ros.nodes.remove(node)
    node.destroy_node()  # logs, does not raise
    assert node.interlock is None


def test_a_beam_cut_by_max_beam_on_s_is_a_warning_until_the_next_exposure(ros):
    """After the watchdog cut a beam left on (the controller died), /diagnostics went on saying OK."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    node = ros.add(SourceControlNode(context=ros.context, parameter_overrides=[Parameter("max_beam_on_s", value=0.5)]))
    probe = ros.node("probe")
    diag = []
    probe.create_subscription(DiagnosticArray, "/diagnostics",
                              lambda m: diag.extend(s for s in m.status if s.name.endswith("x-ray source")), 10)
    pubs = {name: probe.create_publisher(Bool, name, 10)
            for name in ("scan/armed", "source_arm/in_position", "detector_arm/in_position")}
    for pub in pubs.values():
        assert ros.wait_for_subscribers(pub)
    set_beam = probe.create_client(SetBool, "source/set_beam")
    _ready(ros, pubs, node)
    assert ros.call(set_beam, SetBool.Request(data=True)).success

    def keep_reporting():
        for name in ("source_arm/in_position", "detector_arm/in_position"):
            pubs[name].publish(Bool(data=True))
        return not node.beam_on

    assert ros.spin_until(keep_reporting)
    assert ros.spin_until(lambda: keep_reporting() and diag and diag[-1].level == DiagnosticStatus.WARN)
    assert "max_beam_on_s" in diag[-1].message and diag[-1].message.startswith("beam cut: ")
    _ready(ros, pubs, node)
    assert ros.call(set_beam, SetBool.Request(data=True)).success  # the next exposure, shorter than the limit
    assert ros.call(set_beam, SetBool.Request(data=False)).success
    n = len(diag)
    assert ros.spin_until(lambda: keep_reporting() and len(diag) > n)
    assert diag[-1].level == DiagnosticStatus.OK, diag[-1].message


def test_sigterm_to_the_executable_switches_the_beam_off_and_says_so(ros):
    """rclpy's own signal handlers shut the context down before the node was destroyed, so its last word could not
    be published: after SIGTERM with the beam on, source/beam_on stayed true for every subscriber (and a stopped
    scan_orchestrator could not abort: the scan stayed armed and the beam on until max_beam_on_s)."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen([sys.executable, "-m", "robot_ct_ros.nodes.source_control"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        probe = ros.node("probe")
        beam = []
        probe.create_subscription(Bool, "source/beam_on", lambda m: beam.append(m.data), LATCHED)
        pubs = [probe.create_publisher(Bool, name, 10)
                for name in ("scan/armed", "source_arm/in_position", "detector_arm/in_position")]
        probe.create_timer(0.1, lambda: [p.publish(Bool(data=True)) for p in pubs])
        set_beam = probe.create_client(SetBool, "source/set_beam")
        assert ros.wait_for_service(set_beam, 60.0)
        assert ros.spin_until(lambda: ros.call(set_beam, SetBool.Request(data=True), 10.0).success, 20.0)
        assert ros.spin_until(lambda: beam and beam[-1], 10.0)
        proc.send_signal(signal.SIGTERM)
        assert ros.spin_until(lambda: not beam[-1], 10.0), beam
        assert proc.wait(timeout=20) == 0, proc.stderr.read()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)


def _faulty_setup(ros, node_class=SourceControlNode):
    from diagnostic_msgs.msg import DiagnosticArray

    node = ros.add(node_class(context=ros.context, source_factory=SimulatedXraySource))
    probe, pubs, beam, set_beam = _probe(ros)
    diag = []
    probe.create_subscription(DiagnosticArray, "/diagnostics",
                              lambda m: diag.extend(s for s in m.status if s.name.endswith("x-ray source")), 10)
    _ready(ros, pubs, node)
    return node, pubs, diag, beam, set_beam


def test_a_refused_switch_off_is_retried_while_the_interlock_permits_the_beam(ros):
    """set_beam false refused by the driver with the scan armed and both arms in position was never retried (the
    tick retried only what the interlock itself cut, or out of active): the beam stayed on. Now every tick retries."""
    node, pubs, diag, beam, set_beam = _faulty_setup(ros)
    source = node.interlock.source

    def in_position():  # the arms keep reporting, so the interlock never cuts the beam itself
        for name in ("source_arm/in_position", "detector_arm/in_position"):
            pubs[name].publish(Bool(data=True))
        return True

    _ready(ros, pubs, node)
    assert ros.call(set_beam, SetBool.Request(data=True)).success and node.beam_on
    source.fault_off = SourceError("HV controller busy")
    in_position()
    answer = ros.call(set_beam, SetBool.Request(data=False))
    assert not answer.success and "HV controller busy" in answer.message
    tries = source.off_tries
    assert ros.spin_until(lambda: in_position() and source.off_tries >= tries + 3, timeout_s=3.0)
    assert node.beam_on and node.interlock.last_reason == "ok" and node.lifecycle_state == "active"
    source.fault_off = None
    assert ros.spin_until(lambda: not node.beam_on and beam and beam[-1] is False, timeout_s=2.0)
    assert node.interlock.fault == ""


def test_a_driver_exception_other_than_source_error_is_a_fault_and_the_node_lives_on(ros):
    """An OSError (a serial or network driver's) escaped source/set_beam and the 10 Hz tick and ended the executor
    with the beam on. Now it is answered and an ERROR on /diagnostics naming its type; a switch-off is retried."""
    from diagnostic_msgs.msg import DiagnosticStatus

    node, pubs, diag, beam, set_beam = _faulty_setup(ros)
    source = node.interlock.source
    source.fault_on = source.fault_off = OSError("serial port gone")
    answer = ros.call(set_beam, SetBool.Request(data=True))
    assert not answer.success and "OSError: serial port gone" in answer.message and not node.beam_on
    assert ros.spin_until(lambda: diag and diag[-1].level == DiagnosticStatus.ERROR
                          and "OSError: serial port gone" in diag[-1].message)
    source.fault_on = source.fault_off = None
    _ready(ros, pubs, node)
    assert ros.call(set_beam, SetBool.Request(data=True)).success and node.beam_on
    source.fault_on = source.fault_off = TimeoutError("no answer from the HV generator")
    pubs["scan/armed"].publish(Bool(data=False))  # the interlock's cut, in a subscription callback, then every tick
    assert ros.spin_until(lambda: not node.interlock.inputs.scan_armed)
    ros.spin_for(0.3)
    assert node.beam_on and node.lifecycle_state == "active"
    assert ros.spin_until(lambda: diag[-1].level == DiagnosticStatus.ERROR and "TimeoutError" in diag[-1].message)
    source.fault_on = source.fault_off = None
    assert ros.spin_until(lambda: not node.beam_on and beam and beam[-1] is False, timeout_s=2.0)


def test_a_source_that_refuses_to_switch_off_at_shutdown_is_not_reported_off(ros):
    """A shutdown whose switch-off the driver refused logged "beam OFF (finalized)", published source/beam_on false
    and said WARN 'finalized' on /diagnostics with the beam still on. Now the beam state is the driver's, an ERROR
    says the beam may still be on, and the switch-off is retried until the source obeys."""
    from diagnostic_msgs.msg import DiagnosticStatus

    node, pubs, diag, beam, set_beam = _faulty_setup(ros)
    source = node.interlock.source
    assert ros.call(set_beam, SetBool.Request(data=True)).success
    source.fault_off = SourceError("HV controller busy")
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_shutdown() == TransitionCallbackReturn.SUCCESS and node.lifecycle_state == "finalized"
    assert source.beam_on and node.beam_on
    ros.spin_for(0.3)
    assert beam[-1] is True
    assert ros.spin_until(lambda: diag and diag[-1].level == DiagnosticStatus.ERROR
                          and "the beam may still be on" in diag[-1].message
                          and "HV controller busy" in diag[-1].message)
    assert dict((v.key, v.value) for v in diag[-1].values)["beam_on"] == "True"
    tries = source.off_tries
    assert ros.spin_until(lambda: source.off_tries >= tries + 2, timeout_s=2.0)  # still retried
    source.fault_off = None
    assert ros.spin_until(lambda: not source.beam_on and not node.beam_on and beam[-1] is False, timeout_s=2.0)
    n = len(diag)
    assert ros.spin_until(lambda: len(diag) > n)
    assert diag[-1].level == DiagnosticStatus.WARN and diag[-1].message == "finalized"


def test_configure_is_refused_while_a_source_released_on_error_keeps_the_beam_on(ros):
    """A transition that fails (here an unforeseen exception in deactivate) ends in on_error, which releases the
    source; one that refused to switch off is kept aside with the beam on. A configure then must not build a second
    source beside it: it fails, saying why, until the retried switch-off succeeds; then it configures again."""
    class FailingDeactivate(SourceControlNode):
        def on_deactivate(self, state):
            raise RuntimeError("unforeseen fault in a transition")

    node, pubs, diag, beam, set_beam = _faulty_setup(ros, FailingDeactivate)
    source = node.interlock.source
    assert ros.call(set_beam, SetBool.Request(data=True)).success and node.beam_on
    source.fault_off = SourceError("HV controller busy")
    assert node.trigger_deactivate() != TransitionCallbackReturn.SUCCESS
    assert node.lifecycle_state == "unconfigured" and node.interlock is None and node.beam_on
    assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
    assert node.lifecycle_state == "unconfigured" and node.interlock is None
    assert "configure refused" in node.last_error and "HV controller busy" in node.last_error
    source.fault_off = None
    assert ros.spin_until(lambda: not node.beam_on and beam and beam[-1] is False, timeout_s=2.0)
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.interlock is not None and node.interlock.source is not source and not node.beam_on


def test_the_estop_answer_says_the_beam_is_still_on_when_the_source_refused(ros):
    """source/estop answered "e-stop latched, beam off" whatever the driver did: with a switch-off refused, an operator
    was told the beam was off while it was on. Now the answer is the driver's state: success false, the beam still ON
    and the fault, until the source obeys; then "beam off"."""
    node, pubs, diag, beam, set_beam = _faulty_setup(ros)
    source = node.interlock.source
    estop = ros.node("estop_probe").create_client(Trigger, "source/estop")
    assert ros.call(set_beam, SetBool.Request(data=True)).success and node.beam_on
    source.fault_off = SourceError("HV controller busy")
    answer = ros.call(estop, Trigger.Request())
    assert not answer.success and "still ON" in answer.message and "HV controller busy" in answer.message
    assert node.beam_on and node.estop_latched
    source.fault_off = None
    assert ros.spin_until(lambda: not node.beam_on, timeout_s=2.0)
    answer = ros.call(estop, Trigger.Request())
    assert answer.success and answer.message == "e-stop latched, beam off"
