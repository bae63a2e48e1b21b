"""The router's access control as a rule table per role (default deny).

Three tables say everything; :func:`acl_config` only expands them for a profile:

- :data:`RULES`: what a rule allows (zenoh messages, flow, key expressions of the site);
- :data:`ANCHOR_RULES`: the rules every anchor ``<id>`` gets for its own keys only;
- :data:`ROLE_RULES`: which rules each subject (a role, ``anchors``, ``everybody``) has.

With ``S = diffpos/<site>`` and ``L = S/alive`` (liveliness tokens):

========================== ============================================ =====================
rule                        what                                         subjects
========================== ============================================ =====================
``learn-subscribers``       declare_subscriber egress on ``diffpos/**``  everybody
``anchor-<id>``             put ingress ``S/anchor/<id>/state``,         that anchor only
                            ``S/anchor/<id>/range/*``,
                            ``S/anchor/<id>/ranges`` (range batches),
                            ``S/heartbeat/anchor/<id>``;
                            liveliness token ``L/anchor/<id>`` (declare,
                            and query it: the container health check)
``run-control-read``        subscribe ``S/run/control`` (start gate),    anchors
                            ``S/run/clock`` (lockstep clock)
``fusion-publish``          put ingress estimates, diagnostics,          fusion
                            its heartbeat ``S/heartbeat/fusion``;
                            liveliness token ``L/fusion``
``fusion-read``             subscribe ``S/anchor/**`` (states, ranges,   fusion
                            range batches; never truth)
``emulator-publish``        put ingress ``S/truth/**``,                  emulator
                            ``S/run/control``, ``S/run/clock``
``recorder-alive``          liveliness token ``L/recorder`` (declared    recorder
                            once it records: emulate waits for it), its
                            heartbeat ``S/heartbeat/recorder``
``dashboard-alive``         liveliness token ``L/dashboard`` (declared   dashboard
                            once it draws: emulate waits for it), its
                            heartbeat ``S/heartbeat/dashboard``
``read-all``                subscribe ``S/**``                           recorder, dashboard,
                                                                         emulator
``watch-alive``             liveliness subscriber/query on               fusion, recorder,
                            ``L/**``                                     dashboard, emulator
========================== ============================================ =====================

"subscribe" = ``declare_subscriber`` ingress + ``put`` egress on the key expressions.
The ``learn-subscribers`` rule is needed because publishers must learn of subscribers and
zenoh matches declarations by inclusion (``security/README.md``); it reveals subscriptions,
never data.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from diffpos_services.bus.security.profile import ROLES, SecurityProfile, anchor_user
from diffpos_services.wire.keys import Keys

__all__ = ["ANCHOR_RULES", "ROLE_RULES", "RULES", "Rule", "acl_config"]

_SUBSCRIBE = ("declare_subscriber",)
_DELIVER = ("put",)
_PUT = ("put",)
_TOKEN = ("liveliness_token",)
_WATCH = ("declare_liveliness_subscriber", "liveliness_query")


@dataclass(frozen=True)
class Rule:
    """One ``access_control`` rule: ``messages`` in ``flow`` on the key expressions
    ``keys(site_keys)`` (anchor rules: ``keys(site_keys, anchor_id)``), permission allow."""

    id: str
    messages: tuple[str, ...]
    flow: str
    keys: Callable[..., tuple[str, ...]]

    def render(self, rule_id: str, *key_args) -> dict:
        return {
            "id": rule_id,
            "messages": list(self.messages),
            "flows": [self.flow],
            "permission": "allow",
            "key_exprs": list(self.keys(*key_args)),
        }


class _SiteKeys(Keys):
    """:class:`Keys` of a profile's site, which may be a wildcard (``"*"``: every site; the
    profile validated it already)."""

    def __post_init__(self) -> None:
        pass


#: The site-wide rules, in the order they appear in the router file.
RULES: tuple[Rule, ...] = (
    # every key of every site (diffpos/**): subscriptions are matched by inclusion
    Rule("learn-subscribers", _SUBSCRIBE, "egress", lambda k: (_SiteKeys("**").root,)),
    Rule("run-control-read", _SUBSCRIBE, "ingress", lambda k: (k.run_control(), k.run_clock())),
    Rule("run-control-deliver", _DELIVER, "egress", lambda k: (k.run_control(), k.run_clock())),
    Rule("fusion-publish", _PUT, "ingress",
         lambda k: (k.estimates(), k.fusion_diagnostics(), k.heartbeat("fusion"))),
    Rule("fusion-alive", _TOKEN, "ingress", lambda k: (k.alive_fusion(),)),
    Rule("fusion-read-subscribe", _SUBSCRIBE, "ingress", lambda k: k.fusion_inputs()),
    Rule("fusion-read-deliver", _DELIVER, "egress", lambda k: k.fusion_inputs()),
    Rule("emulator-publish", _PUT, "ingress",
         lambda k: (k.truth_all(), k.run_control(), k.run_clock())),
    Rule("recorder-alive", _TOKEN, "ingress", lambda k: (k.alive_recorder(),)),
    Rule("recorder-heartbeat", _PUT, "ingress", lambda k: (k.heartbeat("recorder"),)),
    Rule("dashboard-alive", _TOKEN, "ingress", lambda k: (k.alive_dashboard(),)),
    Rule("dashboard-heartbeat", _PUT, "ingress", lambda k: (k.heartbeat("dashboard"),)),
    Rule("read-all-subscribe", _SUBSCRIBE, "ingress", lambda k: (k.everything(),)),
    Rule("read-all-deliver", _DELIVER, "egress", lambda k: (k.everything(),)),
    Rule("watch-alive-ask", _WATCH, "ingress", lambda k: (k.alive_all(),)),
    Rule("watch-alive-deliver", _TOKEN, "egress", lambda k: (k.alive_all(),)),
)

#: The rules of anchor ``a`` (rule ids ``anchor-<a>-<id>``): its own keys only.
ANCHOR_RULES: tuple[Rule, ...] = (
    Rule("publish", _PUT, "ingress",
         lambda k, a: (k.anchor_state(a), k.anchor_range(a, "*"), k.anchor_range_batch(a),
                       k.heartbeat("anchor", a))),
    Rule("alive", _TOKEN, "ingress", lambda k, a: (k.alive_anchor(a),)),
    # the container health check: a liveliness query for its own token only
    Rule("health-ask", ("liveliness_query",), "ingress", lambda k, a: (k.alive_anchor(a),)),
    Rule("health-answer", _TOKEN, "egress", lambda k, a: (k.alive_anchor(a),)),
)

_WATCH_ALIVE = ("watch-alive-ask", "watch-alive-deliver")
_READ_ALL = ("read-all-subscribe", "read-all-deliver")

#: Subject -> its rules; ``everybody`` = every identity, ``anchors`` = every anchor.
ROLE_RULES: dict[str, tuple[str, ...]] = {
    "everybody": ("learn-subscribers",),
    "anchors": ("run-control-read", "run-control-deliver"),
    "fusion": ("fusion-publish", "fusion-alive", "fusion-read-subscribe", "fusion-read-deliver",
               *_WATCH_ALIVE),
    "recorder": ("recorder-alive", "recorder-heartbeat", *_READ_ALL, *_WATCH_ALIVE),
    "dashboard": ("dashboard-alive", "dashboard-heartbeat", *_READ_ALL, *_WATCH_ALIVE),
    "emulator": ("emulator-publish", *_READ_ALL, *_WATCH_ALIVE),
}


def _subject(subject_id: str, users: list[str], rule_ids: list[str]) -> tuple[dict, dict]:
    return ({"id": subject_id, "usernames": users},
            {"id": subject_id, "rules": rule_ids, "subjects": [subject_id]})


def _subjects(profile: SecurityProfile) -> list[tuple[dict, dict]]:
    """(subject, policy) pairs: everybody, each anchor, all anchors, each role present."""
    ids = profile.identities()
    out = [_subject("everybody", sorted(ids), list(ROLE_RULES["everybody"]))]
    for a in profile.anchors:
        rid = anchor_user(a)
        out.append(_subject(rid, [rid], [f"{rid}-{r.id}" for r in ANCHOR_RULES]))
    if profile.anchors:
        out.append(_subject("anchors", [anchor_user(a) for a in profile.anchors],
                            list(ROLE_RULES["anchors"])))
    for role in ROLES[1:]:
        users = sorted(u for u, (r, _) in ids.items() if r == role)
        if users:
            out.append(_subject(role, users, list(ROLE_RULES[role])))
    return out


def acl_config(profile: SecurityProfile) -> dict:
    """The router's ``access_control`` block (default deny) for ``profile``.

    The tables of this module expanded for the profile's site, anchors and users; rules no
    policy uses are left out. With ``profile.mtls`` every subject also lists
    ``cert_common_names`` equal to its user names (zenoh requires one of each, so a password
    alone no longer suffices).
    """
    keys = _SiteKeys(profile.site)
    rules = [r.render(r.id, keys) for r in RULES]
    for a in profile.anchors:
        rules += [r.render(f"{anchor_user(a)}-{r.id}", keys, a) for r in ANCHOR_RULES]
    pairs = _subjects(profile)
    subjects = [s for s, _ in pairs]
    policies = [p for _, p in pairs]
    if profile.mtls:  # with client certificates, a subject needs the user name AND its certificate
        for subj in subjects:
            subj["cert_common_names"] = list(subj["usernames"])
    used = {r for p in policies for r in p["rules"]}
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [r for r in rules if r["id"] in used],
        "subjects": subjects,
        "policies": policies,
    }
