"""Independent check of the channel emulator with a real ray tracer (Sionna RT, optional extra).

Modules by role: :mod:`.backend` (importing Sionna lazily, :class:`RaytraceUnavailable`),
:mod:`.scene` (building surfaces, the Sionna scene), :mod:`.paths` (interaction chains ->
MPC groups), :mod:`.tracing` (:func:`trace`), :mod:`.dataset` (the ``.npz`` file) and
:mod:`.evaluate` (SNR, first arrival, statistics, comparison with the emulator),
:mod:`.mechanisms` (every traced path -> one of the 18 first-arrival mechanisms of
:mod:`diffpos.paths.model`, or "other" by name, and its length vs the model's closed form) and
:mod:`.mechanism_mix` (the first-arrival mechanism mix, emulator vs ray tracer, with the cause
of every difference). Importing this package does not import Sionna; each name is imported
from the module that defines it (this package re-exports nothing).

The scenario's building is rebuilt as a Sionna RT scene, every anchor x receiver link is
ray traced (line of sight, specular reflection, refraction and first-order edge/wedge
diffraction), each path is classified into the paper's MPC groups 1..4 and the result is
written to a dataset file that ``diffpos reproduce --channel raytrace:FILE`` consumes instead
of the emulator (see :func:`.dataset.load_dataset`, :func:`.evaluate.dataset_first_arrival`).

Scene (all surfaces are *thin* single-sided meshes carrying an ITU-R P.2040 radio material
with the scenario's thickness; Sionna models a wall as one surface, not as a slab):

- facade ``y = 0``: the solid wall below the first window sill and one horizontal strip
  (spandrel) between consecutive window bands; the window bands are *holes*, so the upper and
  lower window edges are free edges (they need ``edge_diffraction=True``);
- side walls ``x = x_1, x_2``, back wall ``y = depth``, floor slabs and roof ``z = floor_z``;
- interior partitions (vertical planes through all floors);
- the ground (``z = 0``, or 1 cm below the lowest anchor if one sits at ``z <= 0``).

Every surface is extended by ``overlap_m`` (5 cm) past each junction, so walls *cross* instead
of merely meeting: surfaces that only touch leak diffracted paths through their free edges.
The partitions are extended too, so they protrude ``overlap_m`` through the window plane.
Windows are open (the paper: plain glass with negligible loss); ``glass_loss_db`` is not
applied. Transmitters are short dipoles along ``radio.polarization`` (Sionna's dipole pattern
minus its 1.76 dBi directivity, i.e. the emulator's normalisation); receivers are isotropic and
dual-polarised (the power of both polarisations is summed), as in the emulator.

Path classification (paper, Table "MPC through the windows"), from Sionna's per-interaction
bit flags (1 specular, 2 diffuse, 4 refraction/transmission, 8 diffraction):

=====  ===========================================  ======================================
group  chains                                       rule
=====  ===========================================  ======================================
1      ``Tx-Rx``, ``Tx-T-Rx``, ...                  no reflection, no diffraction
2      ``Tx-R-Rx`` (also with transmissions)        exactly one reflection, no diffraction
3      ``Tx-D-Rx``, ``Tx-D-T-Rx``, ``Tx-D-T-T-Rx``  diffraction first, then transmissions only
4      everything else                              ``Tx-R-R-..``, ``Tx-D-R-..``, ``Tx-T-D-..``
=====  ===========================================  ======================================

First arrival (paper's definition, identical to :func:`diffpos.channel.emulator.first_arrival`): the
path with the smallest delay among those with ``SNR >= max(P_max - fap_threshold_db,
detection_snr_db)``, SNR = received power + processing gain - kTB.

Known limits of the ray tracer (measured, see docs/raytrace.md): no corner (vertex)
diffraction and first-order diffraction only; transmissions are sampled in proportion to the
transmitted energy, so paths through concrete (about -90 dB per wall, -136 dB per slab) are
found only now and then (harmless: far below the first-arrival threshold), and diffraction
paths that then cross partitions (``Tx-D-T-Rx``) are found only partly at 1e5 samples; the
LLVM backend needs Debian's ``libllvm19`` (LLVM 14 is refused, LLVM 15 aborts).

Dataset file (``numpy.savez_compressed``; N receivers, M anchors, K paths per link, padded;
paths of a link are sorted by delay, the padding has ``path_valid == False``):

=====================  ==============  ======================================================
array                  shape, dtype    meaning
=====================  ==============  ======================================================
``nodes_m``            (N, 3) f8       receiver positions [m]
``anchors_m``          (M, 3) f8       anchor (transmitter) positions [m]
``anchor_ids``         (M,) str        anchor ids
``path_valid``         (N, M, K) bool  a path (before any power threshold)
``path_length_m``      (N, M, K) f8    ``c tau`` [m] (NaN where not valid)
``path_gain_db``       (N, M, K) f4    ``10 log10 sum |a|^2`` over both receive polarisations,
                                       isotropic receiver, 0 dBi dipole transmitter [dB]
``path_aod_deg``       (N, M, K) f4    departure zenith angle at the anchor [deg]
``path_aoa_deg``       (N, M, K) f4    arrival zenith angle (towards the last interaction)
                                       [deg]; 90 = horizontal
``path_chain``         (N, M, K) u2    interaction flags, 4 bits per depth (depth 0 in bits
                                       0-3), see :func:`.paths.chain_label`
``path_class``         (N, M, K) i1    MPC group 1..4 (0 = padding)
``path_vertex_m``      (N, M, K, 3) f4 first interaction point (NaN for ``Tx-Rx``) [m]
``path_vertices_m``    (N, M, K, D, 3) every interaction point in order, D = max depth (NaN
                       f4              past the last); optional: absent in older files
``metadata_json``      () str          JSON: format, scenario (as a dict), solver settings,
                                       versions, run time, the scene surfaces
=====================  ==============  ======================================================

Powers are *not* stored: SNRs are recomputed from ``path_gain_db`` with the scenario's radio
(:func:`.evaluate.path_snr_db`), so a dataset can be re-evaluated for another transmit power or
threshold without re-tracing.
"""
