"""The ROS 2 bridge: a service like the others (liveliness, health with its counters, every input decoded and
validated) that is also one ROS 2 node on the same zenoh network, written as rmw_zenoh writes one (docs/ros2.md):
its node and endpoint liveliness tokens under ``@ros2_lv``, its samples on rmw_zenoh's data keys in CDR with the
33-byte attachment, /tf_static and /robot_description as zenoh-ext advanced publishers with a cache (transient
local: a late subscriber gets the last one).

Its inputs from ROS 2 go where `mfvs task`, `mfvs estop` and a goal from the operator go, as the identity of its
zenoh config (the operator's, behind authority): the controller's task queries, safety's e-stop key (engage only:
releasing it stays a person's explicit `mfvs estop --reset`), vision's set_goal query. Its e-stop goes out from a
realtime process of its own, as the console's (services/safety/estop_sender.py). A ROS stick (sensor_msgs/Joy on
``joy``) and a ROS velocity (geometry_msgs/TwistStamped on ``~/delta_twist_cmds``) go out as a person's jog requests
on jog/request, the one key it produces, which safety takes only while their dead-man is held; behind authority
only the jog identity may put there, so they go out on a session of that identity's (``jog_zenoh``)."""
from __future__ import annotations

import itertools
import queue
import threading
import time
from typing import Callable, Optional

import msgspec
import zenoh
import zenoh.ext

from protocol import messages as m
from protocol.ros2 import cdr
from protocol.ros2.attachment import Attachment, encode as encode_attachment
from protocol.ros2.keys import Distro, Durability, InvalidName, Reliability, check_namespace, check_node_name
from services.controller.task_client import TaskUnavailable, call_task, describe_task
from services.model.arm import ArmDescription, declared_arm
from services.model.kinematics import ArmKinematics
from services.ros2_bridge import core
from services.ros2_bridge.core import Endpoint, InputError
from services.runtime.ports import Port, Ports
from services.runtime.service import Service, ServiceConfig
from services.runtime.threads import start_thread
from services.runtime.transport import GuardedPublisher, ZenohConfig, open_session, publisher_options
from services.safety.estop_sender import EStopSender

#: how often a transient-local publisher says its last sequence number, when it changed (rmw_zenoh's
#: SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD is of this order): a subscriber that missed the sample asks the cache
HEARTBEAT_PERIOD_S = 1.0
#: requests waiting for the stack's answer, at most (a flood of service calls is refused, not queued)
WORK_QUEUE = 8


class Ros2BridgeConfig(ServiceConfig):
    #: ROS_DOMAIN_ID of the ROS 2 graph to join (the first chunk of every rmw_zenoh key)
    domain_id: int = 0
    #: the node's namespace ("/" or "/robot1"): relative topic names (camera/image_raw, joint_states) go under it
    namespace: str = "/"
    node_name: str = "mfvs"
    #: the ROS 2 distribution of the graph's rmw_zenoh: humble (no type hashes), jazzy (rmw_zenoh >= 0.2.4),
    #: kilted, lyrical
    distro: Distro = Distro.JAZZY
    #: the name the stack logs for what ROS 2 asks (the task's ``by``, the e-stop's operator)
    operator: str = "ros2"
    #: how long a service call waits for the controller's answer or safety's confirmation (s)
    action_timeout_s: float = 5.0
    diagnostics_period_s: float = 1.0
    #: publish images while no subscription token for them is visible (rmw_zenoh's older behaviour)
    images_without_subscriber: bool = False
    #: a goal pose's camera is this near the tag at least, this far at most (m)
    goal_min_distance_m: float = 0.05
    goal_max_distance_m: float = 2.0
    #: a ROS stick and velocity as jog requests (services/ros2_bridge/core.py RosJogConfig, docs/ros2.md)
    jog: core.RosJogConfig = msgspec.field(default_factory=core.RosJogConfig)
    #: the zenoh client of the jog identity, whose session alone puts the jog requests (behind authority only it
    #: may: services/runtime/authority.py); null: the bridge's own session (no access control)
    jog_zenoh: Optional[ZenohConfig] = None

    def __post_init__(self) -> None:
        try:
            check_namespace(self.namespace)
            check_node_name(self.node_name)
        except InvalidName as exc:
            raise ValueError(str(exc)) from None
        if isinstance(self.domain_id, bool) or self.domain_id < 0:
            raise ValueError(f"domain_id {self.domain_id}: a non-negative integer (ROS_DOMAIN_ID)")
        if not 0 < self.goal_min_distance_m < self.goal_max_distance_m:
            raise ValueError("goal distances: 0 < goal_min_distance_m < goal_max_distance_m")
        if not 1 <= len(self.operator) <= 64:
            raise ValueError("operator: 1 to 64 characters")


class _Publisher:
    """One ROS 2 publisher: its zenoh publisher, its GID and its sequence numbers, each sample with its
    attachment."""

    def __init__(self, publisher, declared: core.Declared) -> None:
        self._publisher = GuardedPublisher(publisher)
        self.declared = declared
        self._sequence = itertools.count(1)
        # numbered and sent under one lock: /tf is sent from two callbacks (states, features), and a subscriber
        # reads a number lower than the last as a sample from the past
        self._lock = threading.Lock()

    def put(self, message: cdr.Message) -> bool:
        payload = cdr.serialize(message)
        with self._lock:
            attachment = Attachment(next(self._sequence), time.time_ns(), self.declared.gid)
            return self._publisher.put(payload, attachment=encode_attachment(attachment))

    @property
    def heard(self) -> bool:
        """Whether any zenoh subscriber matches the key now: a sample nobody would receive is not even made."""
        return self._publisher.matching

    def undeclare(self) -> None:
        self._publisher.undeclare()


class _Worker:
    """A thread that carries out requests one by one (each may wait seconds for the stack's answer, which a zenoh
    callback must not)."""

    def __init__(self, name: str, stopping: threading.Event) -> None:
        self._queue: queue.Queue = queue.Queue(maxsize=WORK_QUEUE)
        self._stopping = stopping
        self._thread = start_thread(self._run, name)

    def submit(self, job: Callable[[], None]) -> bool:
        try:
            self._queue.put_nowait(job)
            return True
        except queue.Full:
            return False

    def _run(self) -> None:
        while not self._stopping.is_set():
            try:
                job = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            job()
            del job  # nothing of a finished call (its query) is held until the next one

    def join(self) -> None:
        self._thread.join(timeout=10.0)


class Ros2BridgeService(Service):
    name = "ros2_bridge"
    PORTS = Ports(consumes=(Port("camera_image", m.Image), Port("camera_info", m.CameraInfo),
                            Port("robot_state", m.RobotState), Port("features", m.Features),
                            Port("controller_status", m.ControllerStatus), Port("safety_status", m.SafetyStatus),
                            Port("health_all", m.ServiceHealth)),
                  produces=(Port("desired_jog", m.Jog),))

    def __init__(self, config: Optional[Ros2BridgeConfig] = None, **kwargs) -> None:
        super().__init__(config or Ros2BridgeConfig(), **kwargs)
        self.config: Ros2BridgeConfig
        self.graph: Optional[core.NodeGraph] = None
        self._publishers: dict[Endpoint, _Publisher] = {}
        self._lock = threading.Lock()  # the arm, its kinematics, the diagnostics, the subscriber watch
        self._arm: Optional[ArmDescription] = None
        self._kinematics: Optional[ArmKinematics] = None
        self._mount: Optional[m.Pose] = None
        self._diagnostics = core.Diagnostics(self.config.robot_id)
        self._watch = core.SubscriberWatch(self.config.domain_id)
        self._goal_limits = core.GoalLimits(self.config.goal_min_distance_m, self.config.goal_max_distance_m)
        self._estop: Optional[EStopSender] = None
        self._relay = core.JogRelay(self.config.jog)
        self._relay_lock = threading.Lock()  # the relay's stick and sequences: one ROS message at a time
        self._jog_session = None  # the jog identity's, when the config gives one
        self._jog_publisher: Optional[GuardedPublisher] = None
        self._workers: list[_Worker] = []
        self._threads: list[threading.Thread] = []

    # ------------------------------------------------------------------ lifecycle
    def on_start(self) -> None:
        assert self.session is not None
        cfg = self.config
        self.graph = graph = core.NodeGraph.build(cfg.domain_id, cfg.namespace, cfg.node_name, cfg.distro,
                                                  str(self.session.zid()))
        self._estop = EStopSender.for_service(self)
        # the task and goal wait on the controller and vision; the e-stop never waits behind them
        self._task_worker = _Worker("ros2-task", self._stop_event)
        self._estop_worker = _Worker("ros2-estop", self._stop_event)
        self._workers = [self._task_worker, self._estop_worker]
        for endpoint, declared in graph.endpoints.items():
            if endpoint.kind is core.EntityKind.PUBLISHER:
                self._publishers[endpoint] = _Publisher(self._declare_publisher(endpoint, declared.key), declared)
                self._declared.append(self._publishers[endpoint])
        for endpoint, worker, act in ((core.START_TASK, self._task_worker, self._start_task),
                                      (core.STOP_TASK, self._task_worker, self._stop_task),
                                      (core.RESUME_TASK, self._task_worker, self._resume_task),
                                      (core.ESTOP, self._estop_worker, self._engage_estop)):
            self._declared.append(self.session.declare_queryable(
                graph.endpoints[endpoint].key, self._guarded("service", self._service(worker, act)), complete=True))
        self._declared.append(self.session.declare_subscriber(graph.endpoints[core.GOAL_POSE].key,
                                                              self._guarded("goal", self._on_goal)))
        self._start_jog(graph)
        k = self.keys
        self.subscribe(k.camera_image, m.Image, self._on_image, "image")
        self.subscribe(k.camera_info, m.CameraInfo, self._on_camera_info, "camera_info")
        self.subscribe(k.robot_state, m.RobotState, self._on_state, "robot_state")
        self.subscribe(k.features, m.Features, self._on_features, "features")
        self.subscribe(k.controller_status, m.ControllerStatus, self._on_controller, "controller_status")
        self.subscribe(k.safety_status, m.SafetyStatus, self._on_safety, "safety_status")
        self.subscribe(k.health_all, m.ServiceHealth, self._on_health, "health")
        # the ROS graph's subscriptions (rmw_zenoh's graph cache reads the same tokens): history, so the ones
        # declared before the bridge count too
        self._declared.append(self.session.liveliness().declare_subscriber(
            graph.watch_key(), self._guarded("graph", self._on_token), history=True))
        # the tokens last, as rmw_zenoh declares them: a ROS tool that sees the endpoint can use it
        liveliness = self.session.liveliness()
        self._declared.append(liveliness.declare_token(graph.node_token))
        for declared in graph.endpoints.values():
            self._declared.append(liveliness.declare_token(declared.token))
        self._threads = [start_thread(self._diagnostics_loop, "ros2-diagnostics")]
        self.log.info("ROS 2 node %s%s on domain %d (%s), zenoh id %s", cfg.namespace.rstrip("/") + "/",
                      cfg.node_name, cfg.domain_id, cfg.distro.value, graph.zenoh_id)

    def _declare_publisher(self, endpoint: Endpoint, key: str):
        assert self.session is not None
        reliability = (zenoh.Reliability.BEST_EFFORT if endpoint.qos.reliability is Reliability.BEST_EFFORT
                       else zenoh.Reliability.RELIABLE)
        # a bridge never waits on a slow ROS subscriber: the stack's own traffic shares its session
        options = dict(congestion_control=zenoh.CongestionControl.DROP, reliability=reliability)
        if endpoint.qos.durability is not Durability.TRANSIENT_LOCAL:
            return self.session.declare_publisher(key, **options)
        # rmw_zenoh's transient local (rmw_publisher_data.cpp): a cache of depth samples, publisher detection, and
        # for a reliable one sporadic heartbeats so a subscriber that missed the last sample fetches it
        return zenoh.ext.declare_advanced_publisher(
            self.session, key, **options, cache=zenoh.ext.CacheConfig(max_samples=endpoint.qos.depth),
            sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=None,
                                                                sporadic_heartbeat=HEARTBEAT_PERIOD_S),
            publisher_detection=True)

    def _start_jog(self, graph: core.NodeGraph) -> None:
        """The jog requests' publisher (on the jog identity's session when one is configured), then the two ROS
        subscriptions that feed it."""
        assert self.session is not None
        key = self.keys.desired_jog
        self._check_port("produces", key, m.Jog)
        if self.config.jog_zenoh is not None:
            self._jog_session = open_session(self.config.jog_zenoh)
        session = self._jog_session or self.session
        self._jog_publisher = GuardedPublisher.declare(session, key, **publisher_options(key))
        if self._jog_session is None:
            self._declared.append(self._jog_publisher)
        self._declared.append(self.session.declare_subscriber(graph.endpoints[core.JOY].key,
                                                              self._guarded("joy", self._on_joy)))
        self._declared.append(self.session.declare_subscriber(graph.endpoints[core.DELTA_TWIST].key,
                                                              self._guarded("twist", self._on_twist)))

    def on_stop(self) -> None:
        if self._jog_session is not None:  # its own: closed here (a put after this is dropped by its guard)
            self._jog_publisher.undeclare()
            self._jog_session.close()
        for worker in self._workers:
            worker.join()
        for thread in self._threads:
            thread.join(timeout=5.0)
        if self._estop is not None:
            self._estop.close()

    def check_health(self) -> tuple[bool, str]:
        with self._lock:
            arm = self._arm.name if self._arm is not None else "no robot state yet"
            watched = self._image_wanted()
        graph = self.graph
        where = f"{graph.namespace.rstrip('/')}/{graph.node_name} domain {graph.domain_id}" if graph else ""
        estop_ok, estop = self._estop.health() if self._estop is not None else (False, "no e-stop sender")
        return estop_ok, (f"ROS 2 node {where} ({self.config.distro.value}); {arm}; images "
                          f"{'on' if watched else 'off'}; {estop}")

    # ------------------------------------------------------------------ outputs
    def _publish(self, endpoint: Endpoint, message: cdr.Message) -> None:
        if self._publishers[endpoint].put(message):
            self.rates.tick(f"ros.{endpoint.name.strip('/')}")

    def _image_wanted(self) -> bool:
        assert self.graph is not None
        declared = self.graph.endpoints[core.IMAGE]
        return self.config.images_without_subscriber or self._watch.has_subscriber(
            declared.fully_qualified_name, declared.endpoint.ros_type.name)

    def _on_token(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self._watch.on_token(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

    def _on_image(self, image: m.Image, _recv_ns: int) -> None:
        with self._lock:
            wanted = self._image_wanted()
        if not wanted:
            self.counters.inc("images.unwatched")
            return
        self._publish(core.IMAGE, core.image(image))

    def _on_camera_info(self, info: m.CameraInfo, _recv_ns: int) -> None:
        try:
            self._publish(core.CAMERA_INFO, core.camera_info(info))
        except core.Untranslatable as exc:
            self.refuse("camera_info.ros", str(exc))
        with self._lock:
            changed = self._mount != info.camera_in_ee
            self._mount = info.camera_in_ee
        if changed:  # latched: sent when the mounting is first known and when a calibration changes it
            self._publish(core.TF_STATIC, core.camera_mount(info))

    def _on_state(self, state: m.RobotState, _recv_ns: int) -> None:
        # 100 Hz of kinematics and CDR for nobody is most of the bridge's CPU while no ROS tool looks (the
        # description is sent regardless: it is latched for whoever comes)
        joints, tf = self._publishers[core.JOINT_STATES].heard, self._publishers[core.TF].heard
        if self._arm is not None and not (joints or tf):
            self.counters.inc("states.unheard")
            return
        with self._lock:
            arm, why = declared_arm(state.arm, state.arm_digest, len(state.q), None, self._arm)
            if arm is None:
                self.refuse("robot_state.arm", why)
                return
            first = arm is not self._arm
            if first:
                self._arm, self._kinematics = arm, ArmKinematics(arm)
            links = self._kinematics.link_poses(state.q) if tf else None
        if first:
            self._publish(core.ROBOT_DESCRIPTION, core.robot_description(arm))
        if joints:
            self._publish(core.JOINT_STATES, core.joint_state(state, arm))
        if tf:
            self._publish(core.TF, core.arm_tf(links, arm, state.header.stamp_ns))

    def _on_features(self, features: m.Features, _recv_ns: int) -> None:
        tag = core.tag_tf(features) if self._publishers[core.TF].heard else None
        if tag is not None:
            self._publish(core.TF, tag)

    def _on_controller(self, status: m.ControllerStatus, _recv_ns: int) -> None:
        with self._lock:
            self._diagnostics.on_controller(status, time.monotonic_ns())

    def _on_safety(self, status: m.SafetyStatus, _recv_ns: int) -> None:
        with self._lock:
            self._diagnostics.on_safety(status, time.monotonic_ns())

    def _on_health(self, health: m.ServiceHealth, _recv_ns: int) -> None:
        with self._lock:
            self._diagnostics.on_health(health, time.monotonic_ns())

    def _diagnostics_loop(self) -> None:
        while not self._stop_event.wait(self.config.diagnostics_period_s):
            with self._lock:
                array = self._diagnostics.array(time.monotonic_ns(), self.clock.now_ns())
            try:
                self._publish(core.DIAGNOSTICS, array)
            except Exception:  # the session is closing
                if self.stop_requested:
                    return
                self.limited_log.error("diagnostics", "ros2_bridge: could not publish /diagnostics")

    # ------------------------------------------------------------------ inputs
    def _guarded(self, stream: str, callback: Callable[[object], None]) -> Callable[[object], None]:
        """A zenoh callback of a ROS 2 input that counts and logs a failure, as Service.subscribe does for the
        stack's: a bug met by one sample is a counter in the health, not a traceback in zenoh's thread."""
        def guarded(item) -> None:
            try:
                callback(item)
            except Exception:
                self.counters.inc(f"errors.ros.{stream}")
                self.limited_log.error(f"ros:{stream}", "%s: handling a ROS 2 %s failed", self.name, stream)
                self.log.debug("ROS 2 input failure", exc_info=True)
        return guarded

    def _rejected(self, error: InputError, what: str) -> None:
        self.refuse(f"ros.{what}.{error.kind}", str(error))

    def _service(self, worker: _Worker, act: Callable[[], tuple[bool, str]]):
        """A Trigger service's queryable: the request checked here (attachment, CDR), carried out by ``worker``,
        answered with the request's sequence number and client GID."""
        def on_query(query: zenoh.Query) -> None:
            name = self.graph.node_name if self.graph else ""
            try:
                request = core.request_attachment(query.attachment.to_bytes() if query.attachment else None)
                core.trigger_request(query.payload.to_bytes() if query.payload is not None else b"")
            except InputError as exc:
                self._rejected(exc, "service")
                query.reply_err(f"{name}: {exc}"[:512])
                return

            def job() -> None:
                try:
                    success, message = act()
                except Exception as exc:  # the session closing under it, a zenoh error: the caller hears why
                    self.counters.inc("errors.service")
                    success, message = False, f"failed: {exc}"
                reply = core.reply_attachment(request, time.time_ns())
                try:
                    query.reply(query.key_expr, core.trigger_response(success, message[:512]),
                                attachment=encode_attachment(reply))
                except Exception:
                    self.limited_log.warning("reply", "ros2_bridge: could not answer a service call")
                finally:
                    query.drop()  # the caller's get ends now, not when this closure is collected

            if not worker.submit(job):
                self.counters.inc("rejected.ros.service.busy")
                query.reply_err("busy: earlier calls are still waiting for the stack")
        return on_query

    def _task(self, function: str, why: str, session=None) -> tuple[bool, str]:
        self.counters.inc(f"actions.{function}")
        try:
            status = call_task(session or self.session, self.keys, function,
                               m.TaskRequest(operator=self.config.operator, reason=why),
                               self.config.action_timeout_s)
        except TaskUnavailable as exc:
            return False, f"{exc} (is the controller up? may this identity ask it?)"
        return status.ok, describe_task(status)

    def _start_task(self) -> tuple[bool, str]:
        return self._task(m.START_TASK, "ROS 2 service start_task")

    def _stop_task(self) -> tuple[bool, str]:
        return self._task(m.STOP_TASK, "ROS 2 service stop_task")

    def _resume_task(self) -> tuple[bool, str]:
        return self._task(m.RESUME_TASK, "ROS 2 service resume_task")

    def _resume_from_stick(self) -> None:
        """The ROS stick's resume button: asked on the jog identity's session when there is one (behind authority
        the jog identity may resume a task; the bridge's own may too), its answer logged."""
        ok, said = self._task(m.RESUME_TASK, "the ROS 2 stick's resume button", self._jog_session)
        self.counters.inc("jog.resume." + ("done" if ok else "refused"))
        (self.log.info if ok else self.log.warning)("ros2_bridge: the stick's resume button: %s", said)

    def _engage_estop(self) -> tuple[bool, str]:
        self.counters.inc("actions.estop")
        assert self._estop is not None
        status = self._estop.send(False, self.config.operator, "ROS 2 service estop", self.config.action_timeout_s)
        if status is None:
            return False, (f"e-stop sent, but safety did not confirm it within {self.config.action_timeout_s:g} s")
        return True, f"e-stop engaged: safety reports {status.state.value}"

    def _on_goal(self, sample: zenoh.Sample) -> None:
        try:
            core.request_attachment(sample.attachment.to_bytes() if sample.attachment is not None else None)
            pose = core.goal_pose(sample.payload.to_bytes(), self._goal_limits)
            goal = m.VisionGoal(header=self.header("goal"), camera_in_tag=pose)
        except InputError as exc:
            self._rejected(exc, "goal")
            return
        if not self._task_worker.submit(lambda: self._set_goal(goal)):
            self.counters.inc("rejected.ros.goal.busy")

    def _on_joy(self, sample: zenoh.Sample) -> None:
        self._relay_jog(sample, "joy", lambda payload, now_ns: self._relay.joy(payload, now_ns, time.monotonic()))

    def _on_twist(self, sample: zenoh.Sample) -> None:
        self._relay_jog(sample, "twist", self._relay.twist)

    def _relay_jog(self, sample: zenoh.Sample, what: str, relay: Callable[[bytes, int], core.Relayed]) -> None:
        """A ROS stick's or velocity's sample as a jog request, stamped at its receipt; refused (counted, logged at a
        limited rate, nothing sent) when it is no ROS publisher's or not one a jog can be."""
        try:
            core.request_attachment(sample.attachment.to_bytes() if sample.attachment is not None else None)
            with self._relay_lock:
                relayed = relay(sample.payload.to_bytes(), self.clock.now_ns())
                # sent under the lock: two samples must not leave in the other order of their sequence numbers
                sent = self._jog_publisher is not None and self._jog_publisher.put(m.encode(relayed.jog))
        except InputError as exc:
            self._rejected(exc, what)
            return
        if not relayed.stamp_used:
            self.counters.inc(f"ros.{what}.stamp_not_used")
            self.limited_log.warning(f"ros:{what}:stamp", "ros2_bridge: a ROS %s unstamped or stamped more than %g s "
                                     "off the bridge's clock: its device counts as heard at its receipt", what,
                                     self.config.jog.stamp_skew_s)
        if sent:
            self.counters.inc(f"jog.{what}")
            self.rates.tick(f"jog.{what}")
        if relayed.resume and not self._task_worker.submit(self._resume_from_stick):
            self.counters.inc("rejected.ros.joy.resume_busy")

    def _set_goal(self, goal: m.VisionGoal) -> None:
        """The goal to vision through its set_goal query (the operator's, as `mfvs` sends one), whose answer says
        whether vision took it."""
        assert self.session is not None
        for reply in self.session.get(self.keys.vision_api("set_goal"), payload=m.encode(goal),
                                      timeout=self.config.action_timeout_s):
            if reply.ok is None:
                continue
            try:
                answer = m.decode(reply.ok.payload.to_bytes(), m.VisionGoalReply)
            except m.ProtocolError as exc:
                self.refuse("ros.goal.reply", str(exc))
                return
            if answer.ok:
                self.counters.inc("actions.goal")
                self.log.info("goal from ROS 2 set: camera at %s in the tag frame", goal.camera_in_tag.xyz)
            else:
                self.refuse("ros.goal.vision", answer.message)
            return
        self.refuse("ros.goal.unanswered", "vision did not answer set_goal (is it up? may this identity ask?)")
