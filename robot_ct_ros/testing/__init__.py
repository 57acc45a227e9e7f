"""The in-process harness that runs the whole node graph (tests and the demo), and its polling helper."""

from __future__ import annotations

import time

__all__ = ["wait_until"]


def wait_until(predicate, timeout_s: float = 10.0, poll_s: float = 0.005) -> bool:
    """Poll ``predicate`` every ``poll_s`` until it is true or ``timeout_s`` (monotonic) has passed;
    returns its last value as bool (for state that no event announces, e.g. another thread's flag)."""
    end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > end:
            return bool(predicate())
        time.sleep(poll_s)
    return True
