"""The bus layer: everything that knows how a diffpos process joins Zenoh.

- :mod:`.session`: the session policy (explicit endpoints, no multicast), ``--zenoh-config``
  and ``--connect``/``--listen`` options, ``service_settings`` + ``open_session``;
- :mod:`.security`: TLS, user/password and the access rules per role, rendered from a
  security profile (``diffpos security``);
- :mod:`.health`: the liveliness query behind ``diffpos health`` (container health checks);
- :mod:`.commands`: the command lines of bus services started as child processes (the
  recorder's, used by ``diffpos emulate``, tests and benchmarks).

Only this package and the process entry points import zenoh (DEVELOPING.md).
"""
