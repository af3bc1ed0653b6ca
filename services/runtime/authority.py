"""Who may publish what: zenoh deployments in which only the safety service can command the robot and only
robot services can publish robot state, enforced by the router's access control.

Two flavours, written by :func:`write_deployment` (``mfvs authority init``):

* ``acl``: user/password authentication on the router (random passwords, one user per service) and access
  control by user name;
* ``tls``: mutual TLS (a CA, the router's certificate, one client certificate per service, made by
  ``deploy/tls/gen_certs.sh``) and access control by certificate common name.

In both, default permission is deny and each identity may publish only its own keys (:func:`writes`): robot
commands only ``safety``, low-level torque commands only ``torque_controller`` (a controller that does its own
dynamics and so bypasses safety: give that identity only to a tested one), robot state only the robot services,
camera images and the clock only ``robot_sim``, features only ``vision``, the controller's outputs only
``controller``, the e-stop and the goal only ``operator``; queries to the Kinova API functions that move the arm
or change its zones and limits only ``safety`` (everyone may read), the torque-mode setup (Table 5.1's functions)
also ``torque_controller``; a liveliness token and a health key only in
its own name. The rules act on ingress to the router (an egress rule would also drop what the router forwards to
the robot). Services must run as zenoh clients of the
router: access control lives there. The generated files hold secrets (keys, passwords): keep them out of git.
"""
from __future__ import annotations

import json
import os
import secrets
import subprocess
from dataclasses import dataclass
from pathlib import Path

from protocol import kinova
from protocol import messages as m
from protocol.keys import Keys
from services.paths import DEPLOY

DEFAULT_SERVICES = ("safety", "robot_sim", "robot_gateway", "torque_controller", "vision", "controller", "operator",
                    "jog")

#: every message kind zenoh's access control knows; the allow rule must list them all under default deny
_ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
                 "liveliness_query", "declare_liveliness_subscriber"]

_GEN_CERTS = DEPLOY / "tls" / "gen_certs.sh"


@dataclass(frozen=True)
class Deployment:
    router_config: Path
    client_configs: dict[str, Path]
    endpoint: str
    tls: bool


def _camera_keys(keys: Keys) -> list[str]:
    return [keys.camera_image, keys.camera_info]


#: what each identity may publish (put/delete): every key that can cause motion has exactly one writer. The camera
#: keys are robot_sim's, or, in a deployment with the ``camera`` identity (a real camera, `services/camera`), the
#: camera service's alone (robot_sim then renders nothing: scene.camera.enabled false)
def writes(keys: Keys, services=DEFAULT_SERVICES) -> dict[str, list[str]]:
    camera = "camera" in services
    return {
        "robot_sim": ([] if camera else _camera_keys(keys)) + [keys.clock, keys.robot_state, keys.lowlevel_state],
        "camera": _camera_keys(keys) if camera else [],
        "robot_gateway": [keys.robot_state, keys.lowlevel_state],
        "vision": [keys.features],
        "controller": [keys.desired_twist, keys.desired_joint_velocity, keys.controller_status],
        "safety": [keys.robot_command, keys.safety_status],
        "torque_controller": [keys.lowlevel_command],
        # the person (and their tools): the e-stop and its reset, and the goal (which vision validates)
        "operator": [keys.estop, keys.vision_goal],
        # the person's stick (`mfvs jog`): its requests, which safety takes from this identity's source alone
        "jog": [keys.desired_jog],
    }


#: the tools an identity runs under its own credentials, announced in their own names (liveliness token, health):
#: the operator's console (`mfvs console`) and the ROS 2 bridge (`mfvs ros2`) act as the operator and say how they
#: are doing in their own names
TOOLS = {"operator": ("console", "ros2_bridge")}


def announces(identity: str) -> list[str]:
    """The names an identity declares liveliness and health under: its own and its tools'."""
    return [identity, *TOOLS.get(identity, ())]


#: the Kinova API functions anyone may call (they read the arm); the others move it or change its zones/limits
READ_API_FUNCTIONS = sorted(set(kinova.API_FUNCTIONS) - kinova.MUTATING_API_FUNCTIONS)


def queries(keys: Keys) -> dict[str, list[str]]:
    """What each identity may query, beyond what everyone may (:func:`everyone_queries`)."""
    return {"safety": sorted(keys.robot_api(f) for f in kinova.MUTATING_API_FUNCTIONS),
            # the person starts and stops the servo task (the stack comes up idle), and runs the commissioning check
            # (the robot moves itself for it, at their confirmation)
            "operator": [keys.vision_api("set_goal"), keys.vision_api("teach"), keys.controller_api(m.START_TASK),
                         keys.controller_api(m.STOP_TASK), keys.controller_api(m.RESUME_TASK), keys.robot_check_arm],
            # the person goes on with a task their stick paused, by one of its buttons
            "jog": [keys.controller_api(m.RESUME_TASK)],
            # the torque-mode setup (the JACO thesis's Table 5.1) is made by the client that commands the torques
            "torque_controller": sorted(keys.robot_api(f) for f in kinova.TORQUE_SETUP_FUNCTIONS)}


def everyone_queries(keys: Keys) -> list[str]:
    return [keys.robot_api(f) for f in READ_API_FUNCTIONS] + [keys.vision_api("get_goal"),
                                                              keys.controller_api(m.GET_TASK), keys.health_all]


def queryables(keys: Keys, services=DEFAULT_SERVICES) -> dict[str, list[str]]:
    """Who may answer which queries (a rogue queryable could answer in a robot's name)."""
    camera = "camera" in services
    robot = [keys.robot_api_all, keys.robot_check_arm]
    return {"robot_sim": robot + ([] if camera else [keys.camera_info]), "robot_gateway": robot,
            "camera": [keys.camera_info] if camera else [],
            "vision": [keys.vision_api("set_goal"), keys.vision_api("get_goal"), keys.vision_api("teach")],
            "controller": [keys.controller_api(f) for f in m.TASK_FUNCTIONS]}


#: the identity of a lab's ROS 2 nodes (`mfvs authority init --ros2-domain N`): their rmw_zenoh sessions take its
#: client config (ZENOH_SESSION_CONFIG_URI). It and the operator's ROS 2 bridge may use the ROS 2 domains' keys;
#: nothing of mfvs's beyond what every identity may (subscribe, read)
ROS2_IDENTITY = "ros2"
#: who speaks ROS 2 behind authority: the ROS 2 nodes, and the operator, whose tool the bridge is
ROS2_SPEAKERS = (ROS2_IDENTITY, "operator")


def ros2_key_exprs(domains) -> list[str]:
    """The key expressions of ROS 2 domains on rmw_zenoh's wire (docs/ros2.md): each domain's data and service
    keys (``<domain>/...``: no mfvs key starts with a number), zenoh-ext's advanced publishers' cache, heartbeats
    and detection tokens beneath them (``.../@adv/...``: a chunk starting with ``@`` is verbatim, which no
    wildcard includes), and the graph's liveliness tokens (``@ros2_lv/<domain>/...``)."""
    exprs = []
    for domain in domains:
        if isinstance(domain, bool) or not isinstance(domain, int) or domain < 0:
            raise ValueError(f"ROS 2 domain {domain!r}: a non-negative integer (ROS_DOMAIN_ID)")
        exprs += [f"{domain}/**", f"{domain}/**/@adv/**", f"@ros2_lv/{domain}/**"]
    return exprs


def access_control(services, match: str, ros2_domains=()) -> dict:
    """The router's access_control block; ``match`` is "usernames" or "cert_common_names".

    An allow list per identity, under default deny, on ingress (what a client sends to the router): zenoh's access
    control applies a rule to a message whose key expression is *included in* the rule's, so a publication on a
    wildcard (``robot/*``, ``robot/**``, ``robot/comm$*``) is included in no identity's literal keys and is
    denied, where a deny list of literal keys let it through. Egress (what the router forwards to a client) is
    open: the robot must receive safety's commands. With ``ros2_domains``, the ROS 2 speakers
    (:data:`ROS2_SPEAKERS`) may also put, answer, ask and declare liveliness on those domains' keys
    (:func:`ros2_key_exprs`)."""
    services = list(services)
    keys = Keys.all_robots()
    write, query, answer = writes(keys, services), queries(keys), queryables(keys, services)
    rules = [
        {"id": "egress", "permission": "allow", "flows": ["egress"], "messages": _ALL_MESSAGES, "key_exprs": ["**"]},
        {"id": "subscribe_and_reply", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_subscriber", "declare_liveliness_subscriber", "reply"], "key_exprs": ["**"]},
        {"id": "liveliness_query", "permission": "allow", "flows": ["ingress"], "messages": ["liveliness_query"],
         "key_exprs": [keys.liveliness_all]},
        {"id": "read_queries", "permission": "allow", "flows": ["ingress"], "messages": ["query"],
         "key_exprs": everyone_queries(keys)},
    ]
    policies = [{"id": "everyone", "rules": [r["id"] for r in rules], "subjects": services}]
    subjects = []
    for service in services:
        subjects.append({"id": service, match: [service]})
        names = announces(service)
        own = [{"id": f"{service}_writes", "messages": ["put", "delete"],
                "key_exprs": write.get(service, []) + [keys.health(n) for n in names]},
               {"id": f"{service}_alive", "messages": ["liveliness_token"],
                "key_exprs": [keys.liveliness(n) for n in names]},
               {"id": f"{service}_queryables", "messages": ["declare_queryable"],
                "key_exprs": answer.get(service, []) + [keys.health(n) for n in names]}]
        if service in query:
            own.append({"id": f"{service}_queries", "messages": ["query"], "key_exprs": query[service]})
        if ros2_domains and service in ROS2_SPEAKERS:
            # every kind of message: the everyone rules' ``**`` does not include zenoh-ext's ``@adv`` chunks, where
            # a late subscriber asks a latched topic's cache and watches for its publishers
            # and both ways: the egress rule's ``**`` does not include them either (the graph's tokens start with one)
            own.append({"id": f"{service}_ros2", "messages": _ALL_MESSAGES, "key_exprs": ros2_key_exprs(ros2_domains),
                        "flows": ["ingress", "egress"]})
        for rule in own:
            rules.append({"permission": "allow", "flows": ["ingress"], **rule})
        policies.append({"id": f"{service}_own", "rules": [rule["id"] for rule in own], "subjects": [service]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _write(path: Path, data: dict, secret: bool = False) -> Path:
    path.write_text(json.dumps(data, indent=2) + "\n")
    if secret:
        os.chmod(path, 0o600)
    return path


def write_deployment(out_dir, *, tls: bool = False, host: str = "127.0.0.1", port: int = 7447,
                     services=DEFAULT_SERVICES, ros2_domains=()) -> Deployment:
    """Write the router's and every service's zenoh config (and credentials or certificates) into out_dir; with
    ``ros2_domains``, also the ROS 2 nodes' (:data:`ROS2_IDENTITY`)."""
    out = Path(out_dir).resolve()
    ros2_domains = tuple(ros2_domains)
    ros2_key_exprs(ros2_domains)  # refused before anything is written
    clients_dir = out / "clients"
    clients_dir.mkdir(parents=True, exist_ok=True)
    services = list(services) + ([ROS2_IDENTITY] if ros2_domains and ROS2_IDENTITY not in services else [])
    scheme = "tls" if tls else "tcp"
    endpoint = f"{scheme}/{host}:{port}"
    router: dict = {
        "mode": "router",
        "listen": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    clients: dict[str, Path] = {}
    if tls:
        certs = out / "certs"
        subprocess.run(["bash", str(_GEN_CERTS), str(certs), *services], check=True, capture_output=True, text=True)
        router["transport"] = {"link": {"tls": {
            "root_ca_certificate": str(certs / "ca.pem"), "listen_private_key": str(certs / "router.key"),
            "listen_certificate": str(certs / "router.pem"), "enable_mtls": True}}}
        router["access_control"] = access_control(services, "cert_common_names", ros2_domains)
        for service in services:
            clients[service] = _write(clients_dir / f"{service}.json5", {
                "mode": "client", "connect": {"endpoints": [endpoint]},
                "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
                "transport": {"link": {"tls": {
                    "root_ca_certificate": str(certs / "ca.pem"), "enable_mtls": True,
                    "connect_private_key": str(certs / f"{service}.key"),
                    "connect_certificate": str(certs / f"{service}.pem"), "verify_name_on_connect": True}}},
            })
    else:
        passwords = {service: secrets.token_urlsafe(18) for service in services}
        credentials = out / "credentials.txt"
        credentials.write_text("".join(f"{user}:{pw}\n" for user, pw in passwords.items()))
        os.chmod(credentials, 0o600)
        router["transport"] = {"auth": {"usrpwd": {"user": "router", "password": secrets.token_urlsafe(18),
                                                   "dictionary_file": str(credentials)}}}
        router["access_control"] = access_control(services, "usernames", ros2_domains)
        for service, password in passwords.items():
            clients[service] = _write(clients_dir / f"{service}.json5", {
                "mode": "client", "connect": {"endpoints": [endpoint]},
                "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
                "transport": {"auth": {"usrpwd": {"user": service, "password": password}}},
            }, secret=True)
    router_path = _write(out / "router.json5", router, secret=not tls)
    return Deployment(router_path, clients, endpoint, tls)
