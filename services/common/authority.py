"""Who may publish what: zenoh deployments in which only the safety service can command the robot and only
robot services can publish robot state, enforced by the router's access control.

Two flavours, written by :func:`write_deployment` (``mfvs authority init``):

* ``acl``: user/password authentication on the router (random passwords, one user per service) and access
  control by user name;
* ``tls``: mutual TLS (a CA, the router's certificate, one client certificate per service, made by
  ``deploy/tls/gen_certs.sh``) and access control by certificate common name.

In both, default permission is deny; every listed service may do everything except: put/delete on robot
commands (only ``safety``), on low-level torque commands (only ``torque_controller``, a controller that does its
own dynamics and so bypasses safety: give that identity only to a tested one) and on robot state (only the robot
services); and queries to the Kinova API functions that move the arm or change its zones and limits (only
``safety``; everyone may read). Deny rules act on ingress to the router
(an egress deny would also drop what the router forwards to the robot). Services must run as zenoh clients of the
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
from protocol.keys import Keys

COMMANDERS = ("safety",)
ROBOTS = ("robot_sim", "robot_gateway")
TORQUE_CONTROLLERS = ("torque_controller",)
OTHERS = ("vision", "controller", "operator")
DEFAULT_SERVICES = COMMANDERS + ROBOTS + TORQUE_CONTROLLERS + OTHERS

#: every message kind zenoh's access control knows; the allow rule must list them all under default deny
_ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
                 "liveliness_query", "declare_liveliness_subscriber"]

_GEN_CERTS = Path(__file__).resolve().parents[2] / "deploy" / "tls" / "gen_certs.sh"


@dataclass(frozen=True)
class Deployment:
    router_config: Path
    client_configs: dict[str, Path]
    endpoint: str
    tls: bool


def access_control(services, match: str) -> dict:
    """The router's access_control block; ``match`` is "usernames" or "cert_common_names"."""
    services = list(services)
    keys = Keys.all_robots()
    commanders = [s for s in services if s in COMMANDERS]
    robots = [s for s in services if s in ROBOTS]
    torque = [s for s in services if s in TORQUE_CONTROLLERS]
    others = [s for s in services if s not in COMMANDERS + ROBOTS + TORQUE_CONTROLLERS]
    subjects, ids = [], {}
    for group, members in (("commanders", commanders), ("robots", robots), ("torque_controllers", torque),
                           ("others", others)):
        if members:
            subjects.append({"id": group, match: members})
            ids[group] = group
    present = list(ids)
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {"id": "allow_all", "permission": "allow", "flows": ["ingress", "egress"], "messages": _ALL_MESSAGES,
             "key_exprs": ["**"]},
            {"id": "deny_command", "permission": "deny", "flows": ["ingress"], "messages": ["put", "delete"],
             "key_exprs": [keys.robot_command]},
            {"id": "deny_robot_state", "permission": "deny", "flows": ["ingress"], "messages": ["put", "delete"],
             "key_exprs": [keys.robot_state, keys.lowlevel_state]},
            {"id": "deny_torque_command", "permission": "deny", "flows": ["ingress"], "messages": ["put", "delete"],
             "key_exprs": [keys.lowlevel_command]},
            {"id": "deny_robot_api_changes", "permission": "deny", "flows": ["ingress"], "messages": ["query"],
             "key_exprs": sorted(keys.robot_api(f) for f in kinova.MUTATING_API_FUNCTIONS)},
        ],
        "subjects": subjects,
        "policies": [p for p in (
            {"id": "everyone", "rules": ["allow_all"], "subjects": present},
            {"id": "only_safety_commands", "rules": ["deny_command"],
             "subjects": [g for g in present if g != "commanders"]},
            {"id": "only_robots_publish_state", "rules": ["deny_robot_state"],
             "subjects": [g for g in present if g != "robots"]},
            {"id": "only_torque_controllers_command_torques", "rules": ["deny_torque_command"],
             "subjects": [g for g in present if g != "torque_controllers"]},
            {"id": "only_safety_changes_the_robot_through_its_api", "rules": ["deny_robot_api_changes"],
             "subjects": [g for g in present if g != "commanders"]},
        ) if p["subjects"]],
    }


def _write(path: Path, data: dict, secret: bool = False) -> Path:
    path.write_text(json.dumps(data, indent=2) + "\n")
    if secret:
        os.chmod(path, 0o600)
    return path


def write_deployment(out_dir, *, tls: bool = False, host: str = "127.0.0.1", port: int = 7447,
                     services=DEFAULT_SERVICES) -> Deployment:
    """Write the router's and every service's zenoh config (and credentials or certificates) into out_dir."""
    out = Path(out_dir).resolve()
    clients_dir = out / "clients"
    clients_dir.mkdir(parents=True, exist_ok=True)
    services = list(services)
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
        router["access_control"] = access_control(services, "cert_common_names")
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
        router["access_control"] = access_control(services, "usernames")
        for service, password in passwords.items():
            clients[service] = _write(clients_dir / f"{service}.json5", {
                "mode": "client", "connect": {"endpoints": [endpoint]},
                "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
                "transport": {"auth": {"usrpwd": {"user": service, "password": password}}},
            }, secret=True)
    router_path = _write(out / "router.json5", router, secret=not tls)
    return Deployment(router_path, clients, endpoint, tls)
