"""The one-command emulation: router, anchors, fusion (+ recorder, dashboard) as processes.

:class:`.orchestrator.Emulation` starts every service as its own OS process (``python -m
diffpos_services.cli.main <service> ...``, each in its own session so a terminal Ctrl-C reaches
only the orchestrator), waits for readiness by liveliness tokens (never by sleeping), starts
the run by publishing the time base (``RunControl``), publishes ground truth on its own keys,
scores the estimates against the true trajectories, and shuts the services down in order
(anchors, fusion, extras, router last) with SIGTERM, escalating to SIGKILL only if a process
does not exit in time.

Extra services (recorder, dashboard) are hooks: :data:`.options.EXTRA_SERVICES` maps a name to a
function building its command line; one is started only if its CLI module exists.

With ``security_profile`` (``diffpos emulate --security-profile FILE``) the bus is the
secured one of security/README.md: the profile is rendered into a private temporary folder
for a TLS endpoint on a free loopback port; the router loads its configuration (TLS
listener, password dictionary, access control), every child gets its own identity file
(``--zenoh-config <tmp>/<user>.json5``) and the orchestrator logs in as the emulator.

Modules (import each name from its module; this package re-exports nothing):
:mod:`.options` (what runs, the extra services' command lines), :mod:`.orchestrator`
(:class:`Emulation`), :mod:`.monitor` (truth, lockstep clock, estimates, status line),
:mod:`.supervise` (children that die: reported, restarted), :mod:`.notes` (the notes of the
summary), :mod:`.scoring` (:class:`Scorer` over :mod:`diffpos.metrics`, the summary table).
"""
