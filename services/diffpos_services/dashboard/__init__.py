"""dashboard: the Rerun dashboard of a diffpos run (live service and offline converters).

Each name is imported from the module that defines it (no facade); the modules by role:

* :mod:`.building` what is drawn of the building; :mod:`.scenario` reading it from a scenario
* :mod:`.columns` input columns and their builders; :mod:`.decode` partial message views
* :mod:`.geometry` track lookup, ellipsoids, diffraction paths; :mod:`.common` colours, helpers
* :mod:`.scene` building, anchors, truth; :mod:`.estimates` one function per estimate stream;
  :mod:`.events` events and fusion diagnostics; :mod:`.blueprint` the layout
* :mod:`.stream` :class:`Dashboard` (live) and the bulk writers; :mod:`.convert` MCAP -> .rrd
* :mod:`.service` the live dashboard process (bus -> ring buffer -> Rerun, its heartbeat)

Everything here writes to an explicit :class:`rerun.RecordingStream` passed in by the caller
(never the global one), in columns (``send_columns``), so the same code serves

* the live dashboard service (``diffpos dashboard``), which feeds one small batch of bus
  messages at a time into a :class:`Dashboard`, and
* the offline converters (``diffpos to-rerun``, ``diffpos replay --rrd``), which feed a whole
  recording as one batch (:func:`.stream.write_rrd`, :func:`.stream.write_rrd_from_messages`).

All rows are stamped on the **measurement timeline** :data:`.common.TIMELINE` (the ``t_ns`` of the
messages, integer nanoseconds), never on wall-clock time, so a live recording and a replay
of the same run line up sample for sample.

Entity layout (see :func:`.blueprint.default_blueprint` for how it is shown)::

    world                              view coordinates (right-handed, z up), building frame
    world/building/floors              floor outlines (static wireframe)
    world/building/windows             window band (sill and lintel) on the facade y = 0 (static)
    world/anchors/<anchor>             anchor position (Points3D, self-reported AnchorState)
    world/anchors/<anchor>/trail       recent track of the anchor (LineStrips3D)
    world/nodes/<node>/truth           true node position (emulation only)
    world/nodes/<node>/estimate        one marker per responder (Points3D, radius in ui points,
                                       label "<node> F<est>"; on the last fix, grey, "<node>?",
                                       when the newest estimate has no position) and the 95 %
                                       ellipsoid of the fix (Ellipsoids3D)
    world/paths/<node>                 the path of each anchor's mechanism (estimate v2) or
                                       anchor -> window-edge point -> estimate; used anchors in
                                       their colour, gated in red; hidden by the blueprint
                                       until shown per responder (detail on demand)
    metrics/error_3d_m/<node>          |estimate - truth| [m]
    metrics/error_z_m/<node>           estimate z - true z [m]
    metrics/peb_m/<node>               position error bound [m]
    metrics/residual_m/<anchor>        post-fit range residuals of every node (points) [m]
    metrics/gating/excluded            excluded measurements per fusion time (all nodes)
    metrics/gating/used                used measurements per fusion time (all nodes)
    metrics/fusion/<counter>           cumulative fusion counters (FusionDiagnostics)
    floors                             who is on which floor now: per floor the responders, the
                                       floor's probability, the age of the last fix
    events                             text log: anchors joined/left, exclusions with reasons,
                                       status changes (unidentifiable geometry, ...)
"""
