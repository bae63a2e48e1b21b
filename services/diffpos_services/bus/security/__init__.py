"""Zenoh transport security for the diffpos bus: TLS, user/password and access control.

A *security profile* (a small TOML file, see ``security/profile.dev.toml``) names the
certificate files, the credentials dictionary, the site(s) it protects and the anchors that
exist. From it this package renders

- the router's Zenoh configuration (:func:`.configs.router_config`): a TLS listener, a
  ``transport/auth/usrpwd`` dictionary and an ``access_control`` block whose rules say that
  only anchor ``<id>`` (user ``anchor-<id>``) may put ``diffpos/<site>/anchor/<id>/state``
  and ``.../anchor/<id>/range/*``, only the fusion user may put estimates and diagnostics,
  only the emulator may put truth and the run-control gate, and recorder/dashboard only read;
- one client configuration per identity (:func:`.configs.client_config`): TLS trust in the dev CA
  (the client checks the router's name), its own user/password and the router endpoint.

The rules follow the key expressions of :mod:`diffpos_services.wire.keys`; the access control is
enforced by the router (every service is a client of it), default ``deny``.

Modules by role (import each name from its module; this package re-exports nothing):
:mod:`.profile` (the profile and its validation, :class:`.profile.SecurityError`),
:mod:`.credentials` (the password dictionary), :mod:`.acl` (the access rules as a table per
role), :mod:`.configs` (router/client configurations, the configuration a service opens and
its plain-transport warning), :mod:`.render` (json5 files from a profile),
:mod:`.certs` (DEV ONLY certificates), :mod:`.per_run` (fresh secrets for one ``diffpos emulate``
run: the committed dev ones are public).

Zenoh facts this relies on (measured with eclipse-zenoh 1.10.2, see ``security/README.md``):

- a client without credentials, or with a wrong password, is refused when the session is
  established (``zenoh.open`` raises after ``connect/timeout_ms``); it never gets to put;
- an ACL ``declare_subscriber`` *egress* rule must let publishers learn of subscribers
  (clients drop puts nobody subscribes to), and declarations are matched by *inclusion*:
  a recorder's ``diffpos/**`` subscription reaches a publisher only through a rule whose key
  expression includes ``diffpos/**``. That rule reveals subscriptions, never data;
- the dictionary file has one ``user:password`` per line, nothing else (no comments, no
  blank lines: zenoh rejects the file).

Command line (also used to regenerate the committed files)::

    diffpos security certs  OUT_DIR [--host NAME ...] [--client USER ...]
    diffpos security render PROFILE OUT_DIR [--base-dir /security]
        [--connect tls/localhost:7447 --listen tls/127.0.0.1:7447]
    diffpos security check  PROFILE
"""
