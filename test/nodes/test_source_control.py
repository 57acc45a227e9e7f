"""source_control in-process: the beam follows the interlock over real topics and services."""

from std_msgs.msg import Bool
from std_srvs.srv import SetBool, Trigger

from robot_ct_ros.nodes.source_control import LATCHED, SourceControlNode


def _setup(ros):
    node = ros.add(SourceControlNode(context=ros.context))
    probe = ros.node("probe")
    beam = []
    sub = probe.create_subscription(Bool, "source/beam_on", lambda m: beam.append(m.data), LATCHED)
    pubs = {name: probe.create_publisher(Bool, name, 10)
            for name in ("scan/armed", "source_arm/in_position", "detector_arm/in_position", "estop")}
    for pub in pubs.values():
        assert ros.wait_for_subscribers(pub)
    assert ros.wait_for_publishers(sub)
    set_beam = probe.create_client(SetBool, "source/set_beam")
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
    # latched: re-arming alone does not allow the beam
    _ready(ros, pubs, node)
    assert not ros.call(set_beam, SetBool.Request(data=True)).success
    reset = probe.create_client(Trigger, "source/reset_estop")
    assert ros.call(reset, Trigger.Request()).success
    assert ros.call(set_beam, SetBool.Request(data=True)).success


def test_arm_leaving_position_cuts_beam(ros):
    node, probe, pubs, beam, set_beam = _setup(ros)
    _ready(ros, pubs, node)
    assert ros.call(set_beam, SetBool.Request(data=True)).success
    pubs["detector_arm/in_position"].publish(Bool(data=False))
    assert ros.spin_until(lambda: not node.interlock.beam_on)
    assert ros.spin_until(lambda: beam and beam[-1] is False)
