"""Who may use which fleet key: the cloud's Zenoh access control (ACL), made from the key
layout of ``keys.py`` and the identities of a lab's certificates.

The cloud runs as the Zenoh router every robot and tool connects to as a client, so every
message passes its ACL. Subjects are certificate common names (mutual TLS): a robot's
certificate names its id, the operator's names ``operator``. By default everything is
denied; then

    robot <id>  may put on   fleet/<id>/frame, fleet/<id>/keyframe, fleet/<id>/control
                may receive  fleet/<id>/feedback, fleet/<id>/reply
    operator    may put on   fleet/cloud/control (merge, status)
                may receive  fleet/cloud/reply
    cloud-worker  anything on fleet/** (a cloud worker behind the router serves any robot
                and declares the liveliness tokens of the placement)

So a robot can neither publish as another robot (nor end its session) nor read another
robot's poses, and only the operator asks for a merge or the status. Zenoh reads the ACL
at start: the cloud restarts to admit a robot added to the lab.
"""

from __future__ import annotations

from typing import Any

from fleetslam.transport import keys

OPERATOR = "operator"  # the common name of the operator's certificate
WORKER = "cloud-worker"  # the common name of the cloud workers' certificate
_WORKER_MESSAGES = ["put", "delete", "declare_subscriber", "query", "declare_queryable",
                    "reply", "liveliness_token", "declare_liveliness_subscriber",
                    "liveliness_query"]

# What a client sends (ingress at the cloud) and what it may be sent (egress).
_SEND = ["put"]
_RECEIVE = ["declare_subscriber"]


def _rules(name: str, sends: list[str], receives: list[str]) -> list[dict[str, Any]]:
    return [
        {"id": f"{name} sends", "permission": "allow", "flows": ["ingress"],
         "messages": _SEND, "key_exprs": sends},
        {"id": f"{name} subscribes", "permission": "allow", "flows": ["ingress"],
         "messages": _RECEIVE, "key_exprs": receives},
        {"id": f"{name} receives", "permission": "allow", "flows": ["egress"],
         "messages": _SEND, "key_exprs": receives},
    ]


def check_robot_identity(robot: str) -> str:
    """A robot id that can also be a certificate's identity (ValueError if not)."""
    keys.check_robot_id(robot)
    if robot in (OPERATOR, WORKER):
        raise ValueError(f"robot id '{robot}' is the identity of the {robot}s' certificate")
    return robot


def fleet_acl(robots: list[str]) -> dict[str, Any]:
    """The ``access_control`` block of the cloud's Zenoh config for these robot ids."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def allow(name: str, sends: list[str], receives: list[str]) -> None:
        granted = _rules(name, sends, receives)
        rules.extend(granted)
        subjects.append({"id": name, "cert_common_names": [name]})
        policies.append({"id": f"{name} policy", "subjects": [name],
                         "rules": [r["id"] for r in granted]})

    for robot in sorted(set(robots)):
        check_robot_identity(robot)
        allow(robot, [keys.frame(robot), keys.keyframe(robot), keys.control(robot)],
              [keys.feedback(robot), keys.reply(robot)])
    allow(OPERATOR, [keys.CLOUD_CONTROL], [keys.CLOUD_REPLY])
    # Cloud workers behind the router serve any robot: every fleet key, and the liveliness
    # tokens they agree through (cloud/coordination/placement.py).
    rules.append({"id": f"{WORKER} everything", "permission": "allow",
                  "flows": ["ingress", "egress"], "messages": _WORKER_MESSAGES,
                  "key_exprs": [f"{keys.ROOT}/**"]})
    subjects.append({"id": WORKER, "cert_common_names": [WORKER]})
    policies.append({"id": f"{WORKER} policy", "subjects": [WORKER],
                     "rules": [f"{WORKER} everything"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}
