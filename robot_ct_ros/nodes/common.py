"""What every node executable shares: argument handling, spinning and clean shutdown, the topics' QoS."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Callable

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from robot_ct_ros.bag import format as fmt


def run_node(node_factory: Callable[[], "object"], description: str, argv: list[str] | None = None) -> int:
    """Entry point body of a node executable (``ros2 run robot_ct_ros <name>``).

    ``--help`` is answered without starting ROS; ROS arguments (``--ros-args ...``) are
    passed to rclpy untouched. The node spins on a SingleThreadedExecutor (the Jazzy
    wheel's MultiThreadedExecutor is slow, rclpy issue 1452) until SIGINT/SIGTERM, or until it
    shuts its context down itself; the exit status is then its ``exit_code`` (default 0).

    SIGINT and SIGTERM are this function's, not rclpy's: rclpy's handlers shut the context down
    first, so the node's own ``destroy_node`` could no longer publish its last word (the
    orchestrator's abort and ``scan/armed`` false, the source's beam off). Here they stop the
    spin, the node is destroyed while its context is up, and the context is shut down last.
    """
    argv = list(sys.argv if argv is None else argv)
    prog = argv[0].rsplit("/", 1)[-1] if argv else "node"
    user_args = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    parser = argparse.ArgumentParser(
        prog=prog, description=description,
        epilog="ROS arguments follow --ros-args, e.g. --ros-args -p name:=value -r __ns:=/ns")
    parser.parse_args(user_args)

    import signal

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.impl.implementation_singleton import rclpy_implementation
    from rclpy.signals import SignalHandlerOptions

    stopping = []

    def stop(signum, frame):  # a flag, not an exception: one raised inside rclpy's executor could leave it half-way
        stopping.append(signum)

    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except rclpy_implementation.RCLError as exc:  # rcl refused a ROS argument, e.g. "-p name:=" (no value)
        reason = " ".join(str(exc).split("\n")[0].split())
        ros_args = argv[argv.index("--ros-args") + 1:] if "--ros-args" in argv else []
        empty_value = any(a in ("-p", "--param") and b.endswith(":=") for a, b in zip(ros_args, ros_args[1:]))
        hint = "; an empty string value is written -p \"name:=''\"" if empty_value else ""
        print(f"{prog}: bad ROS arguments ({reason}){hint}", file=sys.stderr)
        return 2
    node = None
    previous = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        node = node_factory()
        warn_undeclared_parameters(node)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while rclpy.ok() and not stopping:  # spins in slices, so that a signal is acted on within one
            executor.spin_once(timeout_sec=SIGNAL_POLL_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for s in previous:  # a second signal during the teardown ends the process at once, without a traceback
            signal.signal(s, lambda signum, frame: os._exit(128 + signum))
        try:
            if node is not None:
                node.destroy_node()
        finally:
            shutdown_once(rclpy)
            for s, handler in previous.items():
                signal.signal(s, handler)
    return int(getattr(node, "exit_code", 0) or 0)  # a node that ends itself (replay's exit_when_done) says how


SIGNAL_POLL_S = 0.1
"""How long a node executable's spin waits at most before a SIGINT or SIGTERM is acted on (run_node)."""


def warn_undeclared_parameters(node) -> list[str]:
    """Log a warning naming each parameter ``node`` was given but does not declare, with the declared name
    closest to it, and return those names.

    rclpy ignores such a value without a word, so a misspelt ``itterations:=5`` or a parameter of another node
    ran with the default. Not refused: one parameter file with a ``/**`` section may serve several nodes."""
    import difflib

    declared = [name for name in node._parameters]
    unknown = sorted(name for name in node._parameter_overrides if not node.has_parameter(name))
    if unknown:
        hints = []
        for name in unknown:
            close = difflib.get_close_matches(name, declared, n=1, cutoff=0.6)
            hints.append(f"{name} (did you mean {close[0]}?)" if close else name)
        node.get_logger().warning(f"{len(unknown)} parameter(s) that {node.get_name()} does not have, ignored: "
                                  + ", ".join(hints))
    return unknown


def topic_qos(topic: str, depth: int | None = None) -> QoSProfile:
    """The rclpy QoS profile of ``topic`` as the topic contract states it: bag.format.offered_qos, what a bag records
    as offered (history, depth, reliability, durability; deadlines and liveliness stay rclpy's defaults). ``depth``:
    another history depth, for a subscriber that keeps more than the publisher offers."""
    q = fmt.offered_qos(topic)
    return QoSProfile(history=HistoryPolicy[q.history.name], depth=q.depth if depth is None else int(depth),
                      reliability=ReliabilityPolicy[q.reliability.name],
                      durability=DurabilityPolicy[q.durability.name])


LATCHED = topic_qos(fmt.TOPIC_SCAN_INFO)
"""The latched and state topics' profile (reliable, transient-local, keep-last 1); the nodes' own latched outputs
(reports, slices, scan/status, scan/armed) take it too."""
STREAM = topic_qos(fmt.TOPIC_PROJECTION)
"""The frame and geometry streams' profile (reliable, volatile, keep-last 100)."""


def writable_dir(path, parameter: str) -> Path:
    """``path`` as an absolute folder that exists (made if need be) and can be written, checked when a node starts
    so that a bad place is refused in one line (``parameter ...``, exit status 2) instead of failing with the
    first scan; raises ValueError. The command line's check (jobs.output.prepare_out), named for the parameter."""
    from robot_ct_ros.jobs.output import prepare_out

    try:
        return prepare_out(path, what=f"parameter {parameter}")
    except ValueError as exc:
        message = str(exc)
        raise ValueError(message if message.startswith("parameter ") else f"parameter {parameter}: {message}") from None


def shutdown_once(rclpy, context=None) -> None:
    """``rclpy.try_shutdown`` that tolerates losing the race with rclpy's own SIGINT handler.

    The handler shuts the context down from another thread; when it does so between
    try_shutdown's check and its shutdown call, rcl says "rcl_shutdown already called" and the
    node would exit 1 after a clean stop. Any other error still propagates."""
    from rclpy.impl.implementation_singleton import rclpy_implementation

    try:
        rclpy.try_shutdown(context=context)
    except rclpy_implementation.RCLError as e:
        if "already called" not in str(e):
            raise


def publish_while_up(node, publisher, msg) -> bool:
    """Publish ``msg`` unless ``node``'s context is shut down; returns whether it was published.

    On the way out (destroy_node, a fault) the context may be gone: rclpy's SIGINT handler shuts it
    down from another thread, also between a ``context.ok()`` check and the publish, and rcl then
    says "publisher's context is invalid". There is no one left to tell, and a node stopped by
    SIGINT must still exit 0 (what it does, e.g. switching the beam off, is done before). Any
    publishing error while the context is up still propagates."""
    from rclpy.impl.implementation_singleton import rclpy_implementation

    if not node.context.ok():
        return False
    try:
        publisher.publish(msg)
    except rclpy_implementation.RCLError:
        if node.context.ok():
            raise
        return False
    return True


def service_thread_node_name(owner_name: str, service: str) -> str:
    """The name of the hidden node a :class:`ServiceThread` serves ``service`` from for the node ``owner_name``:
    ``_<owner>_<service with every other character than a letter or digit as _>``."""
    return f"_{owner_name}_" + "".join(c if c.isalnum() else "_" for c in service).strip("_")


class ServiceThread:
    """A service whose callback may block (wait for hardware) without blocking its owner's executor.

    rclpy sends a service's answer when the callback returns, and every callback of a node runs
    on the one executor the node was added to, so a callback waiting for a detector would stall
    every node sharing that executor (the project spins SingleThreadedExecutors: the Jazzy wheel's
    MultiThreadedExecutor busy-loops, rclpy issue 1452, and the test harness and graph.py share one
    executor between all nodes). Here the service belongs to a private hidden node
    (``_<owner>_<name>``, same context and namespace, the owner's resolved and remapped service
    name) spun by its own small MultiThreadedExecutor on a daemon thread; the callback group is
    reentrant, so a second request is answered (e.g. "busy") while a first one waits. The callback
    runs on that thread: it must only touch state the owner guards for it.

    A callback that raises is answered (``success`` false and the reason, for a Trigger/SetBool-like
    response) and reported to ``on_error(reason)`` (e.g. :meth:`WorkerFaults.report`), and so is the
    serving thread ending while the context is still up: the service never dies silently.
    """

    def __init__(self, owner, srv_type, name: str, callback, *, num_threads: int = 2,
                 on_error: Callable[[str], None] | None = None):
        import threading

        import rclpy
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.executors import MultiThreadedExecutor

        self.name = owner.resolve_service_name(name)
        self.node = rclpy.create_node(service_thread_node_name(owner.get_name(), name),
                                      namespace=owner.get_namespace(), context=owner.context, use_global_arguments=False,
                                      start_parameter_services=False)
        self._on_error = on_error or (lambda reason: None)
        self._closing = False

        def guarded(request, response):
            try:
                return callback(request, response)
            except Exception as exc:  # noqa: BLE001 - answered and reported, the service keeps serving
                reason = f"service {self.name} failed: {type(exc).__name__}: {exc}"
                self._on_error(reason)
                if hasattr(response, "success"):
                    response.success = False
                if hasattr(response, "message"):
                    response.message = reason
                return response

        self.service = self.node.create_service(srv_type, self.name, guarded, callback_group=ReentrantCallbackGroup())
        self._executor = MultiThreadedExecutor(num_threads=num_threads, context=owner.context)
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name=f"srv{self.name}", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self._executor.spin()
        except Exception as exc:  # noqa: BLE001 - context shut down (SIGINT), executor shut down, or a fault
            if not self._closing and self.node.context.ok():
                self._on_error(f"service {self.name} thread died: {type(exc).__name__}: {exc}")

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop serving; the caller first releases any callback still waiting."""
        self._closing = True
        self._executor.shutdown(timeout_sec=timeout_s)
        self._thread.join(timeout_s)
        try:
            self.node.destroy_node()
        except Exception:  # noqa: BLE001 - already gone with its context
            pass


class WorkerFaults:
    """Failures of a node's worker threads, handed to its executor: a thread never dies silently.

    A thread calls :meth:`report` (any thread; or runs its body through :meth:`guard`); the
    node's ``on_fault(reason)`` then runs once per report on the executor spinning the node (a
    guard condition wakes it), where the node may publish, log and change its lifecycle state.
    Lifecycle nodes take themselves through their error transition there
    (:func:`error_transition`) and report the reason as an ERROR on /diagnostics.
    """

    def __init__(self, node, on_fault: Callable[[str], None]):
        import threading

        self._lock = threading.Lock()
        self._pending: list[str] = []
        self._on_fault = on_fault
        self._gc = node.create_guard_condition(self._dispatch)

    def report(self, reason: str) -> None:
        with self._lock:
            self._pending.append(reason)
        try:
            self._gc.trigger()
        except Exception:  # noqa: BLE001 - the node is being destroyed: nobody left to tell
            pass

    def guard(self, target: Callable, name: str) -> Callable:
        """``target`` wrapped so that an exception escaping it is reported as "<name> thread died: ..."."""
        def run(*args, **kwargs):
            try:
                return target(*args, **kwargs)
            except Exception as exc:  # noqa: BLE001 - reported, never lost
                self.report(f"{name} thread died: {type(exc).__name__}: {exc}")
        return run

    def _dispatch(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, []
        for reason in pending:
            self._on_fault(reason)


def error_transition(node) -> bool:
    """Take a lifecycle node through its error transition now (call on its executor).

    rclpy runs ``on_error`` when a transition callback answers ERROR; this sets
    ``node.error_transition_pending`` and triggers the transition out of the current primary state
    (active: deactivate; inactive: cleanup), whose callback must answer
    :func:`transition_result` (ERROR while the flag is set). The node's ``on_error`` releases
    everything and answers SUCCESS: it ends unconfigured, to be configured again. Returns whether a
    transition was triggered (not when already unconfigured or finalized)."""
    state = node._state_machine.current_state[1]
    trigger = {"active": node.trigger_deactivate, "inactive": node.trigger_cleanup}.get(state)
    if trigger is None:
        return False
    node.error_transition_pending = True
    try:
        trigger()
    finally:
        node.error_transition_pending = False
    return True


def to_unconfigured(node) -> None:
    """Take a lifecycle node back to unconfigured (deactivate if active, then cleanup; call on its executor)."""
    if node._state_machine.current_state[1] == "active":
        node.trigger_deactivate()
    if node._state_machine.current_state[1] == "inactive":
        node.trigger_cleanup()


def transition_result(node):
    """What a deactivate or cleanup callback answers: ERROR during :func:`error_transition`, else SUCCESS."""
    from rclpy.lifecycle import TransitionCallbackReturn

    return TransitionCallbackReturn.ERROR if getattr(node, "error_transition_pending", False) \
        else TransitionCallbackReturn.SUCCESS


def declare_settings(node, cls, *, prefix: str = "", exclude=(), **defaults):
    """Declare one ROS parameter per field of the settings class ``cls`` (robot_ct_ros.parameters)
    and return the validated instance built from their values.

    Each parameter is ``prefix + ros_name``, typed by its default, with a ParameterDescriptor that
    carries the field's help, unit and, for numbers, its range. Every parameter is read once, here,
    so each is declared read-only: a running node refuses ``ros2 param set`` with rclpy's reason
    instead of reporting a value it does not use (restart the node to change one). ``exclude``:
    fields the node declares its own way (they keep their defaults here). ``defaults`` override field defaults (core units). A value of
    the wrong type or out of range raises ValueError naming the parameter (never a traceback from
    rclpy's internals). List fields (tuple defaults) are double, integer or string arrays; an optional list
    (default None, no ``ros_none``) is an empty array unless given (:func:`declare_optional_array`); an optional
    number, string or flag needs a ``ros_none``."""
    import math

    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
    from rclpy.parameter import Parameter

    from robot_ct_ros.parameters import from_ros_values, specs

    values = {}
    for s in specs(cls):
        if not s.ros or s.name in exclude:
            continue
        name = prefix + s.ros_name
        _refuse_core_unit_name(node, prefix, s)
        unit = f" [{s.ros_unit}]" if s.ros_unit else ""
        extra = f" ({s.to_ros(None) if s.ros_none is not None else ''} = off)" if s.ros_none is not None else ""
        if s.default is None and s.ros_none is None:
            extra = " ([] = unset)"
        choices = f" One of: {', '.join(map(str, s.choices))}." if s.choices else ""
        desc = ParameterDescriptor(name=name, description=f"{s.help}{unit}{extra}{choices}{READ_AT_START}",
                                   read_only=True)
        if s.kind in (int, float) and s.ros_none is None and (s.minimum is not None or s.maximum is not None):
            lo = -math.inf if s.minimum is None else s.to_ros(s.minimum)
            hi = math.inf if s.maximum is None else s.to_ros(s.maximum)
            if s.kind is float:
                desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
            else:  # IntegerRange holds int64 bounds
                desc.integer_range = [IntegerRange(from_value=int(max(lo, -2 ** 63)), to_value=int(min(hi, 2 ** 63 - 1)),
                                                   step=1)]
        default = s.to_ros(defaults.get(s.name, s.default))
        if default is None and s.kind is not tuple:
            raise TypeError(f"{cls.__name__}.{s.name}: an optional number, string or flag needs a ros_none (the ROS "
                            "value that stands for unset): a parameter without a value empties GetParameters")
        if s.kind is float or (s.kind is tuple and s.item_kind is float):
            whole_numbers_as_doubles(node, name, "double" if s.kind is float else "double_array")
        if s.kind is str and s.choices:
            yaml_booleans_as_words(node, name, s.choices)
        refuse_mistyped_file_value(node, name, _unset_parameter_type(s) if default is None or (
            s.kind is tuple and not default) else Parameter.Type.from_parameter_value(default), s.choices or ())
        given_empty = s.kind is tuple and s.item_kind is str and default is not None and given_as_empty_list(node, name)
        try:
            if default is None:  # an optional list with no ROS stand-in: unset is the empty array
                param = declare_optional_array(node, name, _unset_parameter_type(s), desc)
            else:
                param = node.declare_parameter(name, default, desc)
            if given_empty:  # stored with its type: rclpy types an empty list as a byte array
                param = node._parameters[name] = Parameter(name, Parameter.Type.STRING_ARRAY, [])
            values[s.ros_name] = value = param.value
            if (core := s.from_ros(value)) is not None:
                s.check(core)  # this field alone, so the message names the ROS parameter
        except (InvalidParameterTypeException, InvalidParameterValueException, ValueError, TypeError) as exc:
            raise ValueError(f"parameter {name}: {exc}") from None
    try:
        return from_ros_values(cls, values)
    except ValueError as exc:
        raise ValueError(f"{node.get_name()} parameters: {exc}") from None


def refuse_mistyped_file_value(node, name: str, declared, choices=()) -> None:
    """Refuse a value of parameter ``name`` that a ``--params-file`` of ``node`` gives with a type other than
    ``declared`` (an rclpy Parameter.Type), as rclpy refuses it when that file is the only one; raises ValueError
    naming the parameter and the file. Call before declaring ``name``.

    Needed because rcl merges the files in order and keeps the type of the first file that sets a parameter: a
    second file's ``kvp: "ninety"`` over the shipped ``kvp: 90.0`` was dropped and the node ran with 90.0 without a
    word. Every file named in the node's arguments (its context's, unless it ignores them, and its own) is read
    again with yaml; the sections that apply are those rcl applies: the node's fully qualified name, nested
    namespace keys, and the ``/**`` (any namespaces) and ``/*`` (one name) wildcards. Values are typed by rcl's
    rules (a quoted scalar is text; then a boolean word, a whole number, a decimal number). Accepted as the
    declaration itself accepts them: a whole number (or an array of them) for a double (array), see
    :func:`whole_numbers_as_doubles`; a boolean for a text parameter whose ``choices`` name it (``on``, ``off``),
    see :func:`yaml_booleans_as_words`; ``[]`` for any array (rcl reads it as no value)."""
    from rclpy.parameter import Parameter

    T = Parameter.Type
    if declared in (None, T.NOT_SET):
        return
    for path, given, text in params_file_values(node).get(name, ()):
        if given == declared or (given, declared) in ((T.INTEGER, T.DOUBLE), (T.INTEGER_ARRAY, T.DOUBLE_ARRAY)):
            continue
        if given is None and declared.name.endswith("_ARRAY"):  # []
            continue
        if given == T.BOOL and declared == T.STRING and ("on" if text == "True" else "off") in tuple(
                choices() if callable(choices) else choices):
            continue
        given_name = "an empty array" if given is None else f"type '{given.name}'"
        raise ValueError(f"parameter {name}: Trying to set parameter '{name}' to '{text}' of {given_name}, "
                         f"expecting type '{declared.name}' (in {path})")


def params_file_values(node) -> dict:
    """The values the ``--params-file`` files named in ``node``'s arguments give it, by parameter name: a list of
    (file, rclpy Parameter.Type or None for ``[]``, value as text), in the files' order. Read once per node (see
    :func:`refuse_mistyped_file_value` for the sections that apply and how values are typed)."""
    cached = node.__dict__.get("_params_file_values")
    if cached is not None:
        return cached
    import re

    import yaml

    fqn = node.get_fully_qualified_name()
    values: dict = {}
    for path in _params_files(node):
        try:
            root = yaml.compose(Path(path).read_text(), Loader=yaml.SafeLoader)
        except (OSError, yaml.YAMLError):
            continue  # rcl read it when ROS started; a file changed since is not this check's business
        for section, params in _ros_parameter_sections(root, ""):
            pattern = re.escape("/" + section.lstrip("/")).replace(r"/\*\*", "(/[^/]+)*").replace(r"/\*", "/[^/]+")
            if not re.fullmatch(pattern, fqn):
                continue
            for pname, value_node in _flatten_parameters(params, ""):
                values.setdefault(pname, []).append((path, *_rcl_yaml_type(value_node)))
    node.__dict__["_params_file_values"] = values
    return values


def _params_files(node) -> list[str]:
    """The ``--params-file`` paths in ``node``'s arguments: its context's (global) ones unless the node ignores
    them, then its own (``cli_args``), as rcl reads them. rclpy keeps neither list, so they are asked of rcl
    (``rcl_arguments_get_param_files``; the global arguments are the first member of ``rcl_context_t``, the node's
    a member of its ``rcl_node_options_t``). Where that fails, the ``--params-file`` paths of ``sys.argv``."""
    import ctypes

    try:
        rcl, rcutils = ctypes.CDLL("librcl.so"), ctypes.CDLL("librcutils.so")

        class Allocator(ctypes.Structure):
            _fields_ = [(f, ctypes.c_void_p) for f in ("allocate", "deallocate", "reallocate", "zero_allocate",
                                                        "state")]

        class NodeOptions(ctypes.Structure):  # rcl/node_options.h, up to the arguments
            _fields_ = [("allocator", Allocator), ("use_global_arguments", ctypes.c_bool),
                        ("arguments", ctypes.c_void_p)]

        rcutils.rcutils_get_default_allocator.restype = Allocator
        rcl.rcl_arguments_get_param_files_count.argtypes = [ctypes.c_void_p]
        rcl.rcl_arguments_get_param_files_count.restype = ctypes.c_int
        rcl.rcl_arguments_get_param_files.argtypes = [ctypes.c_void_p, Allocator,
                                                      ctypes.POINTER(ctypes.POINTER(ctypes.c_char_p))]
        rcl.rcl_node_get_options.argtypes = [ctypes.c_void_p]
        rcl.rcl_node_get_options.restype = ctypes.c_void_p

        def files(arguments: int) -> list[str]:
            count = rcl.rcl_arguments_get_param_files_count(ctypes.c_void_p(arguments))
            if count <= 0:
                return []
            names = ctypes.POINTER(ctypes.c_char_p)()
            if rcl.rcl_arguments_get_param_files(ctypes.c_void_p(arguments), rcutils.rcutils_get_default_allocator(),
                                                 ctypes.byref(names)) != 0:
                raise OSError("rcl_arguments_get_param_files failed")
            return [names[i].decode() for i in range(count)]  # a few bytes left to rcl's allocator, once per node

        with node.handle:
            options = rcl.rcl_node_get_options(ctypes.c_void_p(node.handle.pointer))
            if not options:
                raise OSError("no node options")
            use_global = NodeOptions.from_address(options).use_global_arguments
            own = files(options + NodeOptions.arguments.offset)
        if not use_global:
            return own
        with node.context.handle:
            return files(node.context.handle.pointer) + own
    except (OSError, AttributeError, ValueError):
        argv = sys.argv[sys.argv.index("--ros-args") + 1:] if "--ros-args" in sys.argv else []
        return [b for a, b in zip(argv, argv[1:]) if a == "--params-file"]


def _ros_parameter_sections(node, prefix: str):
    """(node name, the ``ros__parameters`` mapping node) of each section of a parameter file's yaml node; a key
    above a section is a namespace (``scanner_a: source_control: ros__parameters:``), as rcl reads it."""
    import yaml

    if not isinstance(node, yaml.MappingNode):
        return
    for key, value in node.value:
        if key.value == "ros__parameters":
            yield prefix, value
        else:
            yield from _ros_parameter_sections(value, f"{prefix}/{key.value}" if prefix else key.value)


def _flatten_parameters(node, prefix: str):
    """(dotted parameter name, value yaml node) of each value under a ``ros__parameters`` mapping node."""
    import yaml

    if not isinstance(node, yaml.MappingNode):
        return
    for key, value in node.value:
        name = f"{prefix}.{key.value}" if prefix else key.value
        if isinstance(value, yaml.MappingNode):
            yield from _flatten_parameters(value, name)
        else:
            yield name, value


_RCL_TRUE = ("Y", "y", "yes", "Yes", "YES", "true", "True", "TRUE", "on", "On", "ON")
_RCL_FALSE = ("N", "n", "no", "No", "NO", "false", "False", "FALSE", "off", "Off", "OFF")


def _rcl_yaml_type(value_node):
    """(rclpy Parameter.Type, text) of a parameter's yaml node as rcl's parser types it (rcl_yaml_param_parser:
    a quoted scalar is text; otherwise a boolean word, then a whole number (C's strtoll, any base),
    then a decimal number (strtod, and ``.inf``, ``.nan``), else text). An array is typed by its first item; the
    type is None for ``[]``."""
    import re

    import yaml
    from rclpy.parameter import Parameter

    T = Parameter.Type
    if isinstance(value_node, yaml.SequenceNode):
        if not value_node.value:
            return None, "[]"
        item, _ = _rcl_yaml_type(value_node.value[0])
        array = {T.BOOL: T.BOOL_ARRAY, T.INTEGER: T.INTEGER_ARRAY, T.DOUBLE: T.DOUBLE_ARRAY}.get(item, T.STRING_ARRAY)
        items = ", ".join(v.value if isinstance(v, yaml.ScalarNode) else "?" for v in value_node.value)
        return array, f"[{items}]"
    if not isinstance(value_node, yaml.ScalarNode):
        return T.STRING, "?"
    text = value_node.value
    if value_node.style in ("'", '"'):
        return T.STRING, text
    if text in _RCL_TRUE:
        return T.BOOL, "True"
    if text in _RCL_FALSE:
        return T.BOOL, "False"
    if re.fullmatch(r"[+-]?(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)", text):
        return T.INTEGER, text
    if text in (".nan", ".NaN", ".NAN", ".inf", ".Inf", ".INF", "-.inf", "-.Inf", "-.INF"):
        return T.DOUBLE, text
    try:
        float(text)  # as strtod, but for Python's digit separators
    except ValueError:
        return T.STRING, text
    return (T.STRING, text) if "_" in text else (T.DOUBLE, text)


def _refuse_core_unit_name(node, prefix: str, spec) -> None:
    """Refuse a value given under a setting's command-line name, or its ROS name with the command line's unit, where
    ROS takes it in other units (``exterior_voxel_mm`` for ``exterior_voxel_m``, ``prior_sigma_translation_mm`` for
    ``prior_sigma_translation_m``): ignored with a warning, it ran with the default, and the
    warning's "did you mean" invited the value in mm under the name in metres."""
    if spec.ros_name == spec.name or spec.ros_scale == 1.0:
        return
    names = {spec.name}  # the core name, and the ROS name with the core's unit (prior_sigma_translation_mm)
    if spec.ros_unit and spec.unit and spec.ros_name.endswith("_" + spec.ros_unit):
        names.add(spec.ros_name[:-len(spec.ros_unit)] + spec.unit)
    given = [prefix + n for n in sorted(names) if prefix + n in node._parameter_overrides]
    if not given:
        return
    core = given[0]
    value = node._parameter_overrides[core].value
    try:
        converted = spec.to_ros(tuple(value) if spec.kind is tuple else float(value))
        example = f" ({value} {spec.unit} is {prefix + spec.ros_name}:={converted:g})" if spec.kind is float else \
            f" ({list(value)} {spec.unit} is {prefix + spec.ros_name}:={[round(x, 12) for x in converted]})"
    except (TypeError, ValueError):
        example = ""
    raise ValueError(f"parameter {core}: that is a value in {spec.unit}, the command line's unit; on ROS give "
                     f"{prefix + spec.ros_name}, in {spec.ros_unit}{example}")


READ_AT_START = " Read when the node starts (read-only while it runs)."
"""The end of every parameter's description: nodes read their parameters once (declare_settings)."""


def refuse_unavailable_transitions(node) -> None:
    """Answer a lifecycle ``change_state`` request for a transition the current state does not have with
    ``success`` False, as rclpy does for an unknown label, instead of letting it end the node.

    rclpy 7.1.6 (Jazzy) triggers a transition given by id without checking it, and the state machine's
    RCLError ("Transition is not registered") escapes the service callback and the executor (rclpy
    issue 1209). Wraps the callback of the node's change_state service (``node._service_change_state``,
    a LifecycleNode attribute)."""
    service = node._service_change_state
    answer = service.callback

    def change_state(request, response):
        if not request.transition.label:  # by label, rclpy itself refuses an unknown one
            available = {t[0] for t in node._state_machine.available_transitions}
            if request.transition.id not in available:
                node.get_logger().warning(f"lifecycle transition {request.transition.id} is not available in state "
                                          f"{node._state_machine.current_state[1]!r}: refused")
                response.success = False
                return response
        return answer(request, response)

    service.callback = change_state


def whole_numbers_as_doubles(node, name: str, kind: str) -> None:
    """Let ``-p name:=10`` set a double parameter as ``10.0`` would, and ``[0, 0, 1]`` a double array.

    ROS types a command-line or YAML value by how it is written, so ``10`` is an integer, and rclpy
    refuses an integer override of a parameter declared double ("... of type 'INTEGER', expecting type
    'DOUBLE'"). Call before declaring ``name``; ``kind`` is "double" or "double_array". The override
    is converted, the parameter stays statically typed (a string is still refused). Uses rclpy's
    ``Node._parameter_overrides``, the overrides the node was started with."""
    from rclpy.parameter import Parameter

    T = Parameter.Type
    override = node._parameter_overrides.get(name)
    if override is None:
        return
    if kind == "double" and override.type_ == T.INTEGER:
        node._parameter_overrides[name] = Parameter(name, T.DOUBLE, float(override.value))
    elif kind == "double_array" and override.type_ == T.INTEGER_ARRAY:
        node._parameter_overrides[name] = Parameter(name, T.DOUBLE_ARRAY, [float(v) for v in override.value])


def yaml_booleans_as_words(node, name: str, choices) -> None:
    """Let ``-p exterior:=off`` set a string parameter whose choices include ``off`` (or ``on``): ROS reads a
    value by YAML's rules, where ``off``, ``on``, ``yes`` and ``no`` are booleans, and rclpy refused the boolean for
    a string parameter. A boolean override becomes the choice it was written as (``on`` for true, ``off`` for
    false), where that is a choice; anything else is left for the declaration to refuse. Call before declaring
    ``name`` (rclpy's ``Node._parameter_overrides``, as :func:`whole_numbers_as_doubles`)."""
    from rclpy.parameter import Parameter

    choices = tuple(choices() if callable(choices) else choices)
    override = node._parameter_overrides.get(name)
    if override is None or override.type_ != Parameter.Type.BOOL:
        return
    word = "on" if override.value else "off"
    if word in choices:
        node._parameter_overrides[name] = Parameter(name, Parameter.Type.STRING, word)


def given_as_empty_list(node, name: str) -> bool:
    """Was ``name`` given as ``[]`` (``-p name:=[]``, ``name: []`` in a file)? Then its override is dropped: rcl reads
    an empty list as no value, and rclpy declared the parameter without one (a string list read as "must be
    given"); :func:`declare_settings` stores the empty list instead. Call before declaring ``name`` (rclpy's
    ``Node._parameter_overrides``, as :func:`whole_numbers_as_doubles`)."""
    from rclpy.parameter import Parameter

    override = node._parameter_overrides.get(name)
    if override is None or override.type_ != Parameter.Type.NOT_SET:
        return False
    del node._parameter_overrides[name]
    return True


def _unset_parameter_type(spec):
    """The rclpy Parameter.Type of an optional list setting (declared empty when not given)."""
    from rclpy.parameter import Parameter

    return {int: Parameter.Type.INTEGER_ARRAY, str: Parameter.Type.STRING_ARRAY}.get(spec.item_kind,
                                                                                 Parameter.Type.DOUBLE_ARRAY)


def declare_optional_array(node, name: str, array_type, descriptor):
    """Declare the optional array parameter ``name`` of the rclpy Parameter.Type ``array_type`` (DOUBLE_ARRAY,
    INTEGER_ARRAY); returns the Parameter. Not given (or given as ``[]``, which rcl reads as no value), it holds an
    empty array of that type: unset.

    A parameter declared by its type alone and not given has no value, and rclpy answers a GetParameters request
    that names it with no values at all, also for the other names asked for, so ``ros2 param dump`` (one request
    for every name) would print nothing. rclpy types an empty list as a byte array, so the empty default is stored
    with its type (rclpy's ``Node._parameters``, the declared values; the parameter is read-only)."""
    from rclpy.parameter import Parameter

    param = node.declare_parameter(name, array_type, descriptor)
    if param.type_ == Parameter.Type.NOT_SET:
        param = node._parameters[name] = Parameter(name, array_type, [])
    return param


def publish_diagnostic(node, publisher, level, what: str, hardware_id: str, message: str, values) -> None:
    """Publish one /diagnostics status named ``"<node's fully qualified name>: <what>"``, stamped now.

    ``level`` is a DiagnosticStatus level (OK, WARN, ERROR) or its name in lower case ("ok", "warn",
    "error"); ``values`` (key, value) pairs, each value shown as ``str(value)``."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    if isinstance(level, str):
        level = getattr(DiagnosticStatus, level.upper())

    status = DiagnosticStatus(level=level, name=f"{node.get_fully_qualified_name()}: {what}", hardware_id=hardware_id,
                              message=message, values=[KeyValue(key=k, value=str(v)) for k, v in values])
    msg = DiagnosticArray(status=[status])
    msg.header.stamp = node.get_clock().now().to_msg()
    publisher.publish(msg)


class BadParameters(ValueError):
    """A node refused its parameters (raised out of :func:`run_settings_node`'s node factory)."""


def run_settings_node(node_factory: Callable[[], "object"], description: str, argv: list[str] | None = None) -> int:
    """:func:`run_node` for a node that validates its parameters as it declares them
    (:func:`declare_settings`): a bad value ends the executable with that one-line reason on stderr
    and exit status 2, not a traceback. Any other failure propagates as from :func:`run_node`."""
    def factory():
        try:
            return node_factory()
        except ValueError as exc:
            raise BadParameters(str(exc)) from None

    try:
        return run_node(factory, description, argv)
    except BadParameters as exc:
        argv = list(sys.argv if argv is None else argv)
        prog = argv[0].rsplit("/", 1)[-1] if argv else "node"
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2


# -- settings every lifecycle node shares (appended section: its imports are here) -------------------
from dataclasses import dataclass  # noqa: E402

from robot_ct_ros.parameters import setting, validate  # noqa: E402  (no ROS import)


@dataclass(frozen=True)
class LifecycleSettings:
    """How a lifecycle node starts: ``autostart`` configures and activates it in its constructor, so a
    plain ``ros2 run`` works without a lifecycle manager."""

    autostart: bool = setting(True, "configure and activate at start (no lifecycle manager needed)")

    def __post_init__(self):
        validate(self)
