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
        # names it does not have (controller_node.declare_parameters) instead of ignoring them
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

    def subscription(self, topic: str, callback):
        return self.node.create_subscription(msg_class(R.TYPES[topic]), topic, callback,
                                             qos(topic, subscriber=True))

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
