"""rclpy, loaded when a ROS 2 node starts: the message classes, the QoS of each topic,
``--ros-args`` and the context a node runs in.

Without the ROS 2 wheels (``pip install 'msagv[ros2]'``) :func:`load` raises
:class:`Ros2Unavailable` naming what is missing; nothing else of the project needs them.
"""

from __future__ import annotations

import importlib
import signal

from msagv.bridge import ros_msgs as R


class Ros2Unavailable(RuntimeError):
    """rclpy (or a message package) cannot be imported here; the message says which."""


def load():
    """The ``rclpy`` module, or :class:`Ros2Unavailable`."""
    try:
        import rclpy  # noqa: F401
        import rclpy.executors  # noqa: F401
        import rclpy.node  # noqa: F401
        import rclpy.qos  # noqa: F401
    except Exception as e:  # ImportError, or a wheel whose shared libraries do not load
        raise Ros2Unavailable(f"ROS 2 (rclpy) is not available: {type(e).__name__}: {e}; "
                              f"install it with pip install 'msagv[ros2]'") from None
    return rclpy


def msg_class(typename: str):
    """The rclpy message class of ``pkg/msg/Name`` (:class:`Ros2Unavailable` if its
    package is not installed)."""
    pkg, _, name = typename.split("/")
    try:
        return getattr(importlib.import_module(f"{pkg}.msg"), name)
    except (ImportError, AttributeError) as e:
        raise Ros2Unavailable(f"the ROS 2 message package {pkg} is not installed ({e})") \
            from None


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """Our options and ROS's: everything from ``--ros-args`` on goes to rclpy (remapping
    ``-r odom:=/robot/odom``, parameters ``-p method:=ntwo``, ``--params-file``, ...)."""
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        return argv[:i], argv[i:]
    return list(argv), []


def qos(topic: str, subscriber: bool = False):
    """The QoS of a topic (docs/ROS2.md): reliable, volatile, keep-last 10 (the system
    default of ros2_control's controllers and Nav2); tf keep-last 100; the plan keep-last
    1, offered transient-local and taken volatile (so Nav2's volatile plan publisher
    matches)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    depth = {R.TF: 100, R.PLAN: 1}.get(topic, 10)
    durability = (DurabilityPolicy.TRANSIENT_LOCAL if topic == R.PLAN and not subscriber
                  else DurabilityPolicy.VOLATILE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE, durability=durability)


class Context:
    """One rclpy context with one node and a single-threaded executor; signals are the
    caller's (rclpy's own SIGINT handler is not installed). ``ros_args`` starts with
    ``--ros-args`` (or is empty); ``lifecycle``: the node is an ``rclpy.lifecycle``
    managed node. Close it with :meth:`close`."""

    def __init__(self, node_name: str, ros_args: list[str], lifecycle: bool = False):
        rclpy = load()
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self.rclpy = rclpy
        self.context = rclpy.context.Context()
        handlers = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
        try:
            rclpy.init(args=["msagv"] + list(ros_args), context=self.context,
                       signal_handler_options=SignalHandlerOptions.NO)
        except Exception as e:  # a malformed --ros-args
            raise ValueError(f"--ros-args: {e}") from None
        finally:
            signal.signal(signal.SIGINT, handlers[0])
            signal.signal(signal.SIGTERM, handlers[1])
        # every -p / params-file value becomes a parameter, so that a node can refuse the
        # names it does not have (declare_parameters) instead of ignoring them
        if lifecycle:  # a managed node (rclpy.lifecycle): its state machine and services
            from rclpy.lifecycle import LifecycleNode

            self.node = LifecycleNode(node_name, context=self.context,
                                      automatically_declare_parameters_from_overrides=True)
        else:
            self.node = rclpy.create_node(node_name, context=self.context,
                                          automatically_declare_parameters_from_overrides=True)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def publisher(self, topic: str, typename: str | None = None):
        """A publisher of ``topic`` (its type from :data:`bridge.ros_msgs.TYPES`, or
        ``typename`` for a topic outside it)."""
        return self.node.create_publisher(msg_class(typename or R.TYPES[topic]), topic,
                                          qos(topic))

    def subscription(self, topic: str, callback, matched=None):
        """A subscription to ``topic`` with its QoS; ``matched(info)`` (optional) is called
        as publishers come and go (``info.current_count``: how many are matched now)."""
        events = None
        if matched is not None:
            from rclpy.event_handler import SubscriptionEventCallbacks

            events = SubscriptionEventCallbacks(matched=matched)
        return self.node.create_subscription(msg_class(R.TYPES[topic]), topic, callback,
                                             qos(topic, subscriber=True),
                                             event_callbacks=events)

    def spin_once(self, timeout: float) -> None:
        self.executor.spin_once(timeout_sec=max(0.0, timeout))

    def close(self) -> None:
        try:
            self.executor.shutdown()
            self.node.destroy_node()
        finally:
            try:
                self.rclpy.shutdown(context=self.context)
            except Exception:
                pass


def destroy(node, timers=(), subscriptions=(), services=(), publishers=()) -> None:
    """Take down ``node``'s entities (a managed node's cleanup); a None publisher (one
    never declared) is passed over."""
    for t in timers:
        node.destroy_timer(t)
    for sub in subscriptions:
        node.destroy_subscription(sub)
    for sv in services:
        node.destroy_service(sv)
    for pub in publishers:
        if pub is not None:
            node.destroy_publisher(pub)


class Lifecycle:
    """The transitions of a managed node (``rclpy.lifecycle``), shared by the controller
    and the plant: ``steps`` maps each transition rclpy calls (``configure``, ``activate``,
    ``deactivate``, ``cleanup``, ``shutdown``, ``error``) to the node's function for it.
    A function that raises fails its transition (the node stays where it was) and says why
    once (logged where ``say``; :attr:`error` keeps the reason); every transition is
    recorded in :attr:`done` as ``(name, "success" | "failure")``, in order."""

    def __init__(self, node, steps: dict, log, say: bool = True):
        from rclpy.lifecycle import ManagedEntity, TransitionCallbackReturn

        self.done: list[tuple[str, str]] = []
        self.error: str | None = None
        self.say = say
        run = self._run
        ok, fail = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE
        self._log = log

        class _Entity(ManagedEntity):  # (rclpy calls each entity's on_<transition>)
            def on_configure(self, state):
                return run("configure", steps["configure"], ok, fail)

            def on_activate(self, state):
                return run("activate", steps["activate"], ok, fail)

            def on_deactivate(self, state):
                return run("deactivate", steps["deactivate"], ok, fail)

            def on_cleanup(self, state):
                return run("cleanup", steps["cleanup"], ok, fail)

            def on_shutdown(self, state):
                return run("shutdown", steps["shutdown"], ok, fail)

            def on_error(self, state):
                return run("error", steps["error"], ok, fail)

        node.add_managed_entity(_Entity())

    def _run(self, name: str, fn, ok, fail):
        try:
            fn()
        except Exception as e:  # noqa: BLE001 - a transition that fails says why, once
            self.error = str(e)
            if self.say:
                self._log.error("%s failed: %s", name, e)
            self.done.append((name, "failure"))
            return fail
        self.done.append((name, "success"))
        self._log.info("lifecycle: %s", name)
        return ok

    def summary(self) -> list[dict]:
        """The transitions, for a node's summary (``transitions``)."""
        return [{"transition": n, "result": r} for n, r in self.done]

    @staticmethod
    def label(configured: bool, active: bool, ended: bool) -> str:
        """The lifecycle state: unconfigured, inactive, active or finalized."""
        if ended:
            return "finalized"
        return "active" if active else "inactive" if configured else "unconfigured"


# ---- parameters (both nodes) ------------------------------------------------------------------
ROS_OWN = ("use_sim_time", "start_type_description_service")  # rclpy's own parameters


def parameter_value(name: str, kind, v):
    """A parameter's value as its kind, or ValueError naming it: an integer is a double
    (``-p plan_speed_kmh:=8``), a number list a list of doubles; nothing else converts."""
    num = (int, float)
    if kind is float and isinstance(v, num) and not isinstance(v, bool):
        return float(v)
    if kind is int and isinstance(v, int) and not isinstance(v, bool):
        return int(v)
    if kind is str and isinstance(v, str):
        return v
    if kind is list and not isinstance(v, (str, bytes)):
        try:
            vals = list(v)
        except TypeError:
            vals = None
        if vals is not None and all(isinstance(x, num) and not isinstance(x, bool) for x in vals):
            return [float(x) for x in vals]
    what = {float: "a number", int: "an integer", str: "a string",
            list: "a list of numbers"}[kind]
    raise ValueError(f"ROS parameter {name}: expected {what}, got {v!r}")


def declare_parameters(node, table: dict, defaults: dict) -> dict:
    """Declare every parameter of ``table`` (name -> float, int, str or list) with the
    command line's value as its default; returns the values in force (a ``-p`` override or
    a params file wins; an integer is taken for a double). None for a float: 0. A parameter
    the node does not have (a misspelt name) is refused, naming it, before anything runs
    (the node is created with ``automatically_declare_parameters_from_overrides``, so every
    override is visible). Each is declared with dynamic typing, its kind checked by the node
    itself (:func:`parameter_changes`): ``ros2 param set ... plan_speed_kmh 8`` sends an
    integer, which rclpy's static typing would refuse for a double."""
    from rcl_interfaces.msg import ParameterDescriptor

    given = node.list_parameters([], 10).names
    unknown = sorted(n for n in given if n not in table and n not in ROS_OWN
                     and not n.startswith("qos_overrides."))
    if unknown:
        raise ValueError(f"ROS parameter {unknown[0]}: unknown (known: "
                         f"{', '.join(table)})")
    out = {}
    for name, kind in table.items():
        d = defaults[name]
        if kind is list:
            d = [float(v) for v in d]
        elif kind is float:
            d = float(0.0 if d is None else d)
        elif kind is int:
            d = int(d)
        else:
            d = str(d)
        if node.has_parameter(name):  # given: -p NAME:=VALUE or --params-file
            d = parameter_value(name, kind, node.get_parameter(name).value)
            node.undeclare_parameter(name)  # declared again below, dynamically typed
        try:
            v = node.declare_parameter(name, d, ParameterDescriptor(dynamic_typing=True)).value
        except Exception as e:  # noqa: BLE001 - rclpy's type errors, named
            raise ValueError(f"ROS parameter {name}: {e}") from None
        out[name] = parameter_value(name, kind, v)
    return out


CLOCK_AT_CONFIGURE = "chooses the node's clock at configure; set it while unconfigured"


def parameter_changes(table: dict, current: dict, params, configured: bool,
                      clock_why: str = CLOCK_AT_CONFIGURE) -> tuple[dict, list]:
    """A change of parameters (``ros2 param set``, the SetParameters service) read against
    ``table``: ``(the values it asks for, the names it changes)``, or ValueError with the
    reason (an unknown name, a wrong kind, ``use_sim_time`` while ``configured``: it chose
    the node's clock, ``clock_why``)."""
    new = dict(current)
    for prm in params:
        if prm.name in ROS_OWN:
            if prm.name == "use_sim_time" and configured:
                raise ValueError(f"use_sim_time: {clock_why}")
            continue
        if prm.name not in table:
            raise ValueError(f"{prm.name}: unknown")
        new[prm.name] = parameter_value(prm.name, table[prm.name], prm.value)
    return new, [k for k in table if new[k] != current[k]]


def set_parameters_result(ok: bool, reason: str = ""):
    """rcl_interfaces' answer to a parameter change."""
    from rcl_interfaces.msg import SetParametersResult

    return SetParametersResult(successful=ok, reason=reason.removeprefix("ROS parameter "))


# ---- diagnostics and services (both nodes) ----------------------------------------------------
DIAGNOSTICS = "/diagnostics"  # where diagnostic_updater publishes, absolute
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
DIAGNOSTICS_PERIOD = 1.0  # s, on a steady clock (diagnostic_updater's default period)
OK, WARN, ERROR, STALE = 0, 1, 2, 3  # diagnostic_msgs/DiagnosticStatus levels


class Diagnostics:
    """A node's status on ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, one
    DiagnosticStatus named ``"<node>: <what>"``) every :data:`DIAGNOSTICS_PERIOD` on a
    steady clock (also when /clock stalls): ``status()`` gives ``(level, message, values)``,
    the values as strings. Without diagnostic_msgs installed it says so once and publishes
    nothing (:attr:`pub` None)."""

    def __init__(self, node, what: str, hardware_id: str, status, log):
        from rclpy.clock import Clock, ClockType

        self.node, self.what, self.hardware_id, self.status = node, what, hardware_id, status
        self.pub = self.timer = None
        try:
            self.pub = node.create_publisher(msg_class(DIAGNOSTICS_TYPE), DIAGNOSTICS, 10)
            self.timer = node.create_timer(DIAGNOSTICS_PERIOD, self.publish,
                                           clock=Clock(clock_type=ClockType.STEADY_TIME))
        except Ros2Unavailable as e:
            log.warning("no %s: %s (pip install ros-diagnostic-msgs)", DIAGNOSTICS, e)

    def publish(self) -> None:
        level, message, values = self.status()
        st = msg_class("diagnostic_msgs/msg/DiagnosticStatus")()
        st.level = bytes([level])
        st.name = f"{self.node.get_name()}: {self.what}"
        st.message = message
        st.hardware_id = self.hardware_id
        kv = msg_class("diagnostic_msgs/msg/KeyValue")
        st.values = [kv(key=k, value=x) for k, x in values.items()]
        m = msg_class(DIAGNOSTICS_TYPE)()
        m.header.stamp = self.node.get_clock().now().to_msg()
        m.status = [st]
        self.pub.publish(m)

    def destroy(self) -> None:
        destroy(self.node, [t for t in (self.timer,) if t is not None], (), (), (self.pub,))
        self.pub = self.timer = None


def trigger_services(node, callbacks: dict, log) -> list:
    """``~/<name>`` std_srvs/Trigger services, one per ``callbacks`` entry; none (said once)
    without std_srvs installed."""
    try:
        import std_srvs.srv as srv
    except ImportError as e:
        log.warning("no %s services: %s (pip install ros-std-srvs)",
                    " and ".join(f"~/{n}" for n in callbacks), e)
        return []
    return [node.create_service(srv.Trigger, f"~/{n}", cb) for n, cb in callbacks.items()]
