"""Launch-free ROS test harness: every test gets its own rclpy context on its own domain.

Nodes run in-process on a SingleThreadedExecutor (the Jazzy wheel's MultiThreadedExecutor
is slow, rclpy issue 1452). Discovery is limited to localhost so parallel runs on one
machine, or other machines on the network, never see each other's traffic.
"""

from __future__ import annotations

import itertools
import os
import signal
import time

import pytest

_domain_counter = itertools.count()


@pytest.fixture(autouse=True, scope="session")
def _sigint_reaches_child_processes():
    """Tests stop child processes with SIGINT (Ctrl-C). A shell that starts the test run in the
    background leaves SIGINT ignored, and an ignored signal stays ignored across exec in every
    child; a handled one is reset to the default there."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield


def _next_domain_id() -> int:
    # Distinct per test and per pytest process; 1..200 keeps FastDDS ports in range.
    return 1 + (os.getpid() * 7 + next(_domain_counter)) % 200


class RosHarness:
    """One rclpy context, one executor, and the nodes added to it."""

    def __init__(self, domain_id: int):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.domain_id = domain_id
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes = []

    def node(self, name: str, **kwargs):
        """A plain helper node on this context (for test publishers, subscribers, clients)."""
        import rclpy

        return self.add(rclpy.create_node(name, context=self.context, **kwargs))

    def add(self, node):
        self.executor.add_node(node)
        self.nodes.append(node)
        return node

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=min(0.02, max(0.0, end - time.monotonic())))

    def spin_until(self, predicate, timeout_s: float = 10.0) -> bool:
        """Spin until ``predicate()`` is true; returns False on timeout (the test then asserts)."""
        end = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > end:
                return False
            self.executor.spin_once(timeout_sec=0.02)
        return True

    def wait_for_subscribers(self, publisher, count: int = 1, timeout_s: float = 10.0) -> bool:
        """Wait until ``publisher`` has matched ``count`` subscriptions, so nothing published is lost."""
        return self.spin_until(lambda: publisher.get_subscription_count() >= count, timeout_s)

    def wait_for_publishers(self, subscription, count: int = 1, timeout_s: float = 10.0) -> bool:
        return self.spin_until(lambda: subscription.get_publisher_count() >= count, timeout_s)

    def wait_for_service(self, client, timeout_s: float = 10.0) -> bool:
        return self.spin_until(client.service_is_ready, timeout_s)

    def call(self, client, request, timeout_s: float = 10.0):
        """Call a service and spin until the answer arrives; raises on timeout."""
        if not self.wait_for_service(client, timeout_s):
            raise TimeoutError(f"service {client.srv_name} not available")
        future = client.call_async(request)
        if not self.spin_until(future.done, timeout_s):
            raise TimeoutError(f"service {client.srv_name} did not answer")
        return future.result()

    def shutdown(self) -> None:
        import rclpy

        for node in self.nodes:
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def ros(monkeypatch):
    """A fresh rclpy context on a unique ROS_DOMAIN_ID, localhost-only discovery."""
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    domain_id = _next_domain_id()
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain_id))
    harness = RosHarness(domain_id)
    try:
        yield harness
    finally:
        harness.shutdown()
