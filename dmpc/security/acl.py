"""Zenoh access control generated from a scenario: each role may touch only its own keys.

The rules follow the protocol of ``bus.keys`` (``R`` is the run id, ``*`` for any run):

=============  =====================================  ==========================================
role           may publish (put, liveliness token)    may subscribe to
=============  =====================================  ==========================================
agent-I        plan/I, kept/I, ready/I;               release, plan/J for J in N_I, control,
               token alive/agent-I                    alive/*
coordinator    release, control, inputs, telemetry/*,  plan/*, kept/*, ready/*, state/*, setpoint/*,
               setpoint-answer/*;                     alive/*
               token alive/coordinator;
               queryable setpoint/* and its replies
               (relays as a router: plan/*, alive/*)
plant          state/plant; token alive/plant         inputs, control, alive/*
sensor-I       state/sensor-I; token alive/sensor-I   inputs, control, alive/*
router         relays: everything under dmpc/R/**     everything under dmpc/R/**
observer       nothing                                telemetry/*, alive/* (``dmpc watch``)
operator       setpoint/* (a put or a query)          setpoint-answer/*, alive/* (``dmpc setpoint``)
=============  =====================================  ==========================================

Subjects are bound to certificate common names (the roles of ``dmpc.security.certs``), the
default is deny, and the rules hold on ingress: a node filters what its links bring in, which
is the direction an honest node controls. Egress rules let each node hand a role only what
that role may subscribe to, and the declarations it needs to see. Denied messages vanish
silently (Zenoh reports nothing to the sender of a put; a denied query ends without a reply).

Every role sees the coordinator's queryable on ``setpoint/*`` (a declaration), but only an
operator's query gets through: any other role's ends at once without a reply, which ``dmpc
setpoint`` reports as "not authorised or no run listening".
"""
from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

from dmpc.bus import keys

ACL_FILE = "acl.json"
# everything the protocol sends; the one queryable is the coordinator's, for setpoint requests
_DECLARES = ["declare_subscriber", "declare_queryable", "liveliness_token", "declare_liveliness_subscriber"]
_ALL = ["put", "delete", "query", "reply", "liveliness_query", *_DECLARES]


def _rule(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": key_exprs}


def access_control(names: Sequence[str], neighbours: Mapping[str, Sequence[str]], run_id: str = "*") -> dict:
    """The ``access_control`` section of a Zenoh configuration.

    Parameters
    ----------
    names : sequence of str
        Subsystem (agent) names.
    neighbours : mapping name -> names
        N_I without I: whose plans agent I subscribes to.
    run_id : str
        The run's key prefix chunk; ``*`` accepts any run of this scenario.

    Returns
    -------
    dict
        JSON-ready: ``enabled``, ``default_permission`` (deny), ``rules``, ``subjects``,
        ``policies``.
    """
    if run_id != "*":
        keys.check_chunk(run_id, "run id")
    R = run_id
    root = f"{keys.ROOT}/{R}/**"
    alive_all = keys.alive_prefix(R)
    rules, subjects, policies = [], [], []

    def role(name: str, puts: list[str], subs: list[str], tokens: list[str], receives: list[str],
             more: Sequence[str] = ()) -> None:
        rid = name
        rules.extend([
            _rule(f"{rid} put", "ingress", ["put"], puts),
            _rule(f"{rid} subscribe", "ingress", ["declare_subscriber"], subs),
            _rule(f"{rid} token", "ingress", ["liveliness_token"], tokens),
            _rule(f"{rid} watch", "ingress", ["declare_liveliness_subscriber", "liveliness_query"], [alive_all]),
            _rule(f"{rid} receive", "egress", ["put"], receives),
        ])
        subjects.append({"id": rid, "cert_common_names": [name]})
        policies.append({"id": rid, "rules": [f"{rid} put", f"{rid} subscribe", f"{rid} token", f"{rid} watch",
                                              f"{rid} receive", "declarations", *more], "subjects": [rid]})

    rules.append(_rule("declarations", "egress", _DECLARES + ["liveliness_query"], [root]))
    # In the star topology the coordinator's session is the agents' router: it forwards their
    # plans and liveliness tokens, which every agent already checked at that first hop. So the
    # coordinator may bring in plans and tokens of any role; it is the run's root of trust anyway.
    states = keys.state_prefix(R)
    setpoints, answers = keys.setpoint_prefix(R), keys.setpoint_answer(R, "*")
    kept = keys.kept(R, "*")
    # the coordinator answers setpoint requests sent as queries: its queryable and its replies come in
    # from it, and an operator's queries go out to it
    rules.extend([_rule("coordinator answers", "ingress", ["declare_queryable", "reply"], [setpoints]),
                  _rule("coordinator asked", "egress", ["query"], [setpoints])])
    role(keys.COORDINATOR_ROLE, [keys.release(R), keys.control(R), keys.inputs(R), keys.plan(R, "*"), kept,
                                 keys.telemetry_prefix(R), answers],
         [keys.plan(R, "*"), kept, keys.ready(R, "*"), states, setpoints], [alive_all],
         [keys.plan(R, "*"), kept, keys.ready(R, "*"), states, setpoints], ["coordinator answers", "coordinator asked"])
    # the plant, or one sensor per subsystem, may publish its own state and nothing else
    for source in keys.state_sources(names):
        subs = [keys.inputs(R), keys.control(R)]
        role(source, [keys.state(R, source)], subs, [keys.alive(R, source)], subs)
    for name in names:
        own = keys.agent_role(name)
        subs = [keys.release(R), keys.control(R)] + [keys.plan(R, j) for j in neighbours[name]]
        role(own, [keys.plan(R, name), keys.kept(R, name), keys.ready(R, name)], subs, [keys.alive(R, own)], subs)
    # an observer only listens: it may declare subscribers to the telemetry and watch tokens
    telemetry = keys.telemetry_prefix(R)
    rules.extend([_rule("observer subscribe", "ingress", ["declare_subscriber"], [telemetry]),
                  _rule("observer watch", "ingress", ["declare_liveliness_subscriber", "liveliness_query"],
                        [alive_all]),
                  _rule("observer receive", "egress", ["put"], [telemetry])])
    subjects.append({"id": "observer", "cert_common_names": ["observer"]})
    policies.append({"id": "observer", "rules": ["observer subscribe", "observer watch", "observer receive",
                                                 "declarations"], "subjects": ["observer"]})
    # an operator (a supervisory program) may request setpoints and hear the answers, nothing else;
    # any sender name under its certificate: it names the program, the certificate the role
    rules.extend([_rule("operator put", "ingress", ["put", "query"], [setpoints]),
                  _rule("operator subscribe", "ingress", ["declare_subscriber"], [answers]),
                  _rule("operator watch", "ingress", ["declare_liveliness_subscriber", "liveliness_query"],
                        [alive_all]),
                  _rule("operator receive", "egress", ["put"], [answers]),
                  _rule("operator replies", "egress", ["reply"], [setpoints])])
    subjects.append({"id": keys.OPERATOR_ROLE, "cert_common_names": [keys.OPERATOR_ROLE]})
    policies.append({"id": keys.OPERATOR_ROLE, "rules": ["operator put", "operator subscribe", "operator watch",
                                                         "operator receive", "operator replies", "declarations"],
                     "subjects": [keys.OPERATOR_ROLE]})
    rules.extend([_rule("relay in", "ingress", _ALL, [root]), _rule("relay out", "egress", _ALL, [root])])
    subjects.append({"id": "router", "cert_common_names": ["router"]})
    policies.append({"id": "router", "rules": ["relay in", "relay out"], "subjects": ["router"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def scenario_access_control(system, run_id: str = "*") -> dict:
    """:func:`access_control` for the subsystems and graph of ``system`` (a ``CoupledSystem``), bound to
    the run ``run_id`` (``*``: any run)."""
    names = [s.name for s in system.subsystems]
    neighbours = {names[i]: [names[j] for j in system.neighbours[i] if j != i] for i in range(system.M)}
    return access_control(names, neighbours, run_id)


def write_acl(directory: str | Path, acl: dict) -> Path:
    """Write the access control ``acl`` as ``acl.json`` to ``directory``; its path."""
    path = Path(directory) / ACL_FILE
    path.write_text(json.dumps(acl, indent=1))
    return path


def read_acl(directory: str | Path) -> dict | None:
    """The ``acl.json`` of a certificate directory, or None if there is none.

    Raises
    ------
    ValueError
        The file is not a JSON object with the keys of an access control section.
    """
    path = Path(directory) / ACL_FILE
    if not path.is_file():
        return None
    try:
        acl = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not JSON ({exc})") from None
    if not isinstance(acl, dict) or not {"rules", "subjects", "policies"} <= set(acl):
        raise ValueError(f"{path}: not an access control section (needs rules, subjects, policies)")
    return acl
