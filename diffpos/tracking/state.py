"""Types of the per-responder tracker (:mod:`diffpos.tracking.tracker`) and its hypothesis layout.

:class:`TrackerConfig` (constants), :class:`TrackerState` (filter bank of every node),
:class:`TrackOutput` (published estimate), :class:`TrackStatus`; the layout of the hypotheses
``h = mode * F + floor`` (mode 0 level, 1 vertical: :func:`hypothesis_floor`,
:func:`hypothesis_vertical`, :func:`n_floors_of`) and the floor marginal
(:func:`floor_probabilities`). Imports nothing from the other tracking modules, so that each of
them can use it.
"""

from __future__ import annotations

import enum
import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.channel.detection import normal_cdf
from diffpos.paths.mechanisms import DIFFRACTION_SLOTS

__all__ = [
    "SNR_CACHE_LINKS",
    "SNR_CACHE_SLOTS",
    "FloatArray",
    "TrackOutput",
    "TrackStatus",
    "TrackerConfig",
    "TrackerState",
    "clamp_to_floor",
    "credible_floor_weights",
    "few_ranges",
    "floor_contested",
    "floor_probabilities",
    "floor_reweighted",
    "has_position",
    "height_band_bound",
    "hypothesis_floor",
    "hypothesis_vertical",
    "mixture_mse_cov",
    "n_floors_of",
    "published_floor_probabilities",
    "robust_floor_log_prob",
]

FloatArray = NDArray[np.float64]
#: Links per hypothesis whose SNR predictions the state keeps (:class:`TrackerState`): the
#: first this many anchor columns of an update (the others are predicted every time).
SNR_CACHE_LINKS = 16
#: The slots whose predicted SNR the state keeps: the direct slot, then the diffraction ones
#: (:data:`diffpos.paths.mechanisms.DIFFRACTION_SLOTS`), ~85 % of a link's prediction; the window-band
#: slots are cheap and near a band edge: predicted every update.
SNR_CACHE_SLOTS = (0, *DIFFRACTION_SLOTS)


class TrackStatus(enum.IntEnum):
    """Status of one node's track (stored as int8 in :attr:`TrackerState.status`)."""

    UNINITIALISED = 0
    """No snapshot yet (too few ranges so far): no position."""
    INITIALISING = 1
    """Initialised from a snapshot, not yet confirmed by ``confirm_epochs`` updates."""
    TRACKING = 2
    COASTING = 3
    """No usable ranges this epoch: predicted only, the covariance grows."""
    LOST = 4
    """No usable ranges for ``lost_after_s``: no position published until re-initialised."""


def has_position(status: NDArray) -> NDArray[np.bool_]:
    """Where a track has a position to publish: its :class:`TrackStatus` ``status`` is
    neither UNINITIALISED nor LOST (two comparisons: ``np.isin``'s setup costs ~20 us, several
    calls per tracker call)."""
    return (status != TrackStatus.UNINITIALISED) & (status != TrackStatus.LOST)


@dataclass(frozen=True)
class TrackerConfig:
    """Tracker constants (the docstrings of :mod:`diffpos.tracking.tracker`,
    :mod:`diffpos.tracking.imm` and :mod:`diffpos.tracking.tracker` give the physical
    source of each).

    Attributes
    ----------
    q_h_m2_s3, q_v_m2_s3 : float [m^2/s^3]
        White-acceleration spectral densities, horizontal and vertical (both modes; measured:
        a stiffer level mode, 0.01 m^2/s^3, pinned early wrong-floor locks for longer).
    v_level_sigma_m_s : float [m/s]
        Vertical speed standard deviation given to a state entering the level mode (the end of
        a flight: the carry's bobbing, ~0.1 m/s).
    v_stairs_m_s : float [m/s]
        Vertical speed on stairs; sets the adjacent-floor transition probability.
    jump_rate_hz : float [1/s]
        Rate of a jump to any floor (re-acquisition after a wrong lock).
    z_mix_sigma_m : float [m]
        Height standard deviation added when a state is mixed into another floor.
    z_margin_m : float [m]
        A floor hypothesis' position is kept ``margin`` inside its floor's box (walls, floor,
        ceiling).
    box_sigma_m : float [m]
        Standard deviation of the box pseudo-measurement applied outside the box.
    exist_margin_m : float [m]
        A specular path whose entry point is within this distance of the window band's
        boundary may or may not exist (the entry point's uncertainty): the smallest margin;
        while tracking, a hypothesis' margin also grows with its own height uncertainty
        (:func:`diffpos.tracking.model.existence_margin`).
    height_sigma_m, stairs_weight : float [m], [-]
        Device height above the floor in the level mode: the building's nominal node height
        (hand/chest carry, +- ``height_sigma_m``), a pseudo-measurement of every epoch (the
        ranges alone observe the height weakly: with 4 anchors a track drifted 1.5 m in z along
        a family of mechanism combinations with small residuals); in the vertical mode
        anywhere between floor and ceiling. ``stairs_weight``: the long-run fraction of time in
        the vertical mode (sets the rate of entering it, see :mod:`diffpos.tracking.imm`; also the
        mode prior at initialisation).
    sigma_model_m : float [m]
        Model error added to every range sigma (anchor navigation error).
    outlier_weight : float [-]
        Prior probability that a range is none of the modelled mechanisms.
    outlier_span_m : float [m]
        Width of the one-sided outlier density.
    mixing : {"select", "imm"}
        How a floor's prior is formed from the previous floors: ``"select"`` continues every
        floor from its most probable predecessor (its own state unless a neighbour moving in
        is more probable than staying: a floor that the data has not yet decided keeps its own
        position instead of being dragged towards a different position on another floor);
        ``"imm"`` moment-matches all predecessors (the classic IMM interaction).
    gn_iterations : int
    select_passes : int
        Mechanism selections per update: the first at the prior mean, each further one at the
        previous pass' fit (then the IEKF restarts from the prior).
    init_grid_m : float [m]
        Grid step of the snapshot initialisation.
    init_starts : int
        Best grid cells per floor refined by the IEKF at initialisation.
    init_sigma_v_m_s : float [m/s]
        Initial velocity standard deviation (walking speed).
    start_grid_m : float [m]
        Grid step (and the IEKF prior's spread, as ``init_grid_m``'s) of the snapshot that
        starts a node's track (its first epoch with ``min_ranges_init`` ranges, and a restart
        after LOST or divergence); the re-seeds' snapshots keep ``init_grid_m``. 0: ``init_grid_m``
        (off, the default). Why: a track's first snapshot decides its run (a walker's outcome is
        bistable in the epoch and place its true floor's track starts from:
        docs/tracking_evidence.md "Session 24: start-up lock-in"), and the coarse grid's
        ranking widens every range by ``(init_grid_m / 2)^2``, which at 2 m fits an out-of-model
        first arrival (1-2 m long) with a wrong mechanism instead of calling it an outlier, so
        the best cells of the true floor lie 3-5 m from the node; the start runs once per node,
        so its finer grid (4x the cells at half the step) is paid once. Measured at 1.0 (the
        grid step before 06f1b49; docs/tracking_evidence.md "Session 27: start-up"): Sionna
        paper 89.56 -> 91.30 % right floor over ten seeds (start-up misses 342 -> 101; one
        seed -4.5), the 3-UAV building 75.08 -> 77.07 %, Sionna ``large`` 93.35 -> 93.27 %,
        the main command 96.69 -> 96.70 %, 16 random buildings 99.65 -> 99.41 % (one at
        0.56 % confidently wrong): not the default.
    min_ranges_init : int
    confirm_epochs : int
    lost_after_s : float [s]
    nis_limit : float [-]
        Limit of the averaged NIS per used range (divergence).
    nis_alpha : float [-]
        Weight of the newest epoch in the NIS average.
    diverge_epochs : int
    reseed_epochs : int
        Consecutive bad epochs after which a floor hypothesis is re-seeded from a snapshot of
        its floor (so every floor keeps the best explanation of the data on that floor).
    reseed_max : int
        At most this many floor hypotheses of a node are re-seeded per epoch (bounded cost;
        per node since 2026-12-07, so rows stay independent: before, per call); 0: none.
        Default 2 (with ``reseed_min_links`` 4) since 2026-12-07: on Sionna RT's live paper
        building (five noise seeds, lockstep, unbounded steps) right floor 84.91 -> 87.28 %,
        better on every seed, no floor published wrongly at p >= 0.95; the 3-UAV building
        identical, Sionna ``large`` 91.01 / 0.97 -> 90.93 / 1.06 %, the main command's
        twelve seeds 91.30 / 1.03 -> 91.13 / 1.06 %, the emulator's 30 s ``large`` identical;
        the tracker's CPU on ``large`` +10 % (docs/tracking_evidence.md "Session 24").
        Before: 0 (measured then on the default and large scenarios: it changed no floor
        decision, and a snapshot cost ~0.1-0.3 s per node-floor).
    dormant : bool
        Skip the measurement update of hypotheses the data has decided against (*dormant*,
        see :mod:`diffpos.tracking.tracker`); False: every hypothesis of every
        node is updated every epoch.
    dormant_margin_nats : float [nats]
        A hypothesis becomes dormant when its posterior probability is below the mass the
        floor jump alone gives it every epoch (``jump_rate_hz dt / (F - 1)``) by this margin
        (3 nats: a 20:1 likelihood ratio against it in the epoch).
    dormant_refresh_s : float [s]
        A dormant hypothesis gets a real update at least this often (measurement time;
        hypothesis ``h`` on its own phase ``h / H`` of the period, so the refreshes of one
        node are spread over the period).
    dormant_epochs : int
        Consecutive real updates below the threshold before a hypothesis becomes dormant
        The real update that refreshes or wakes a dormant hypothesis does not count: its
        state is up to ``dormant_refresh_s`` stale, so its broad prior and unconverged fit
        cost it several nats in that epoch alone (measured: judged on that update, a
        wrong-floor lock of other-building never recovered; judged on it without the excess
        Occam factor, floor 89.2 % against 91.3 % for the full run over 28 runs), so it is
        awake for at least one more update.
    dormant_floor_p : float [-]
        A node whose most probable floor (predicted, marginal over the modes) is below this
        probability is not confident: every hypothesis of it is updated. Default 0 (off):
        measured with 0.99 (the fusion's ``CONFIDENT_FLOOR_PROBABILITY``), 28 runs of
        default and other-building: floor 91.4 % against 91.6 % without it and 91.3 % with
        no dormant hypotheses; but ranges only (the soak), most nodes are not that sure of
        their floor and the 200 x 16 tracker cost rose from ~0.27 to 0.36 ms per node-epoch.
    floor_evidence_lag1_corr : float [-]
        Correlation ``rho`` of one epoch's floor evidence with the next's; the *published*
        floor probabilities are tempered by ``kappa = (1 + rho) / (1 - rho)``
        (:func:`published_floor_probabilities`; 0: untempered). The filter itself, the chosen
        floor, the position and its covariance do not use it.
    snr_reuse_m, snr_reuse_anchor_m : float [m]
        Default 0.05 / 0.1 m: the reuse is on (an approximation). A hypothesis' predicted
        SNRs of the slots :data:`SNR_CACHE_SLOTS` (direct and diffraction) of its first
        :data:`SNR_CACHE_LINKS` links (:func:`diffpos.tracking.model.snr_cost_near`; the SNR
        prediction was ~30 % of the tracker's CPU) are reused while its prior is within
        ``snr_reuse_m`` of the point they were predicted at (that point stays until the
        prior leaves the margin) and a link's while its anchor is within
        ``snr_reuse_anchor_m`` of the anchor they were predicted for (matched by position,
        whatever the link's column); the window-band slots are predicted every update
        (:class:`TrackerState`'s ``snr_*`` fields). Both 0: never reused, the cache not even
        read (the exact predictions, bit for bit; measured: the soak and large replays'
        estimates identical to the code before).
        Measured (2026-11-27, 2-core VM, load 1-4.5), 0.05 / 0.1 m against exact:
        ``bench_accuracy.py --only default large tall-floors wide-windows uavs-above-windows
        anchors-beyond-ends`` within the run-to-run spread but anchors-beyond-ends' 3D p90,
        0.224 m in 3 exact runs, 0.229 m in 4 (its floor 98.61-98.89 % and cov95 94.3-95.1 %
        vs 98.61 % and 94.63 %), outside that scenario's run-to-run spread (the commit that
        added these figures, 030d875, says 'off' but left the defaults at 0.05 / 0.1);
        0.02 / 0.05 m kept 0.224 m but saved nothing on the soak.
        CPU (replay of the 30 s 16 x 200 soak, all epochs, no recorded decisions): 0.49 ->
        0.44-0.45 ms per node-epoch; the predictions reused are 49 % of the soak's links,
        6.5 % of the walkers' (``large``).
    snr_cost_cap_nats : float [nats]
        Cap of one slot's SNR cost (:func:`diffpos.tracking.model.cap_snr_cost`: a robust SNR
        likelihood, the amplitude model being the emulator's); 0: no cap (before).
    link_learn : bool
        Learn every hypothesis' unmodelled-path component per link
        (:mod:`diffpos.tracking.evidence`: its weight and excess delay); False: the fixed
        outlier component of ``outlier_weight`` / ``outlier_span_m`` (before).
    link_forget : float [-]
        Forgetting factor of the learned outlier counts per real update.
    link_prior_updates : float [updates]
        Strength of the outlier weight's Beta prior (mean ``outlier_weight``).
    link_outlier_max : float [-]
        Upper bound of a learned outlier weight.
    link_bias_learn : bool
        The outlier component includes the learned excess delay (False: the learned weight
        only, with the fixed uniform density).
    link_bias_q_m2_s : float [m^2/s]
        Random walk of a learned excess delay.
    link_snr_gain : float [-]
        Gain of the learned outlier SNR's running mean.
    link_match_m : float [m]
        An anchor within this distance of a learned link's last anchor position is that link.
    link_learn_minority : bool
        (``link_learn``) A hypothesis' learned outlier counts (and its evidence shares) take
        only its real updates in which fewer than half of the node's ranges are outliers
        (``2 n_out < n_meas``, the test of ``family_minority`` and of a bad epoch): a
        hypothesis that calls most of its ranges outliers has a wrong state (a track's start,
        a dormant hypothesis woken stale), not that many out-of-model links, and learning from
        it raises the outlier weight of every link at once, which the hypothesis then pays on
        every range once its state is right (the inlier weight ``log(1 - eps)``, up to
        ``log 0.5`` per range). The link's last fit (``link_fit``) is kept either way; a
        skipped update leaves the counts as they were (nothing forgotten). Default False
        (every real update, as before): measured (docs/tracking_evidence.md "Learning from a
        wrong state") it mends the README's main command at seeds 1 and 3 (+3.2, +3.7
        points right floor) but costs Sionna's live paper building 10.6 points (88.15 ->
        77.59 %; there two of four links are often out of the model).
    link_learn_unexplained : bool
        (``link_learn``) A node's learned outlier weights are used (above the prior
        ``outlier_weight``) only while its track has learned that its channel has first
        arrivals out of the path model (the test of ``family_learned_links``:
        :func:`diffpos.tracking.evidence.unexplained_log_odds` > 0); before that its links
        have the prior weight. The counts are learned either way. Default False (always
        used, as before): measured (docs/tracking_evidence.md "Learning from a wrong state")
        the main command's seeds 1-4 gain 0.2-5.9 points right floor (seed 2's confidently
        wrong 2.59 -> 3.33 %), but Sionna's live paper building loses 3.1 points (88.15 ->
        85.09 %: a track's first seconds, before the counts favour the out-of-model channel)
        and heldout-2 (three ranges: never counted, so never open) 3.6 (69.35 -> 65.74 %,
        confidently wrong 0.65 -> 1.85 %).
    lost_on_gap : bool
        A node whose last update with ranges is more than ``lost_after_s`` before this
        epoch is LOST before the update (re-initialised from a snapshot with every floor
        alive when it has ``min_ranges_init`` ranges, INITIALISING until ``confirm_epochs``;
        else no position), however long ago the tracker was last called for it: after a
        stall (the fusion stopped, no epochs at all) its state is stale. False (before): the
        first epoch after the gap updated the stale track (predicted over the whole gap, the
        floor probabilities those of before the gap) and published it TRACKING.
    min_anchors_tracking : int
        A node updated with fewer ranges than this in an epoch is published COASTING, not
        TRACKING, and its published floor probabilities are capped
        (``few_anchors_floor_p_max``): two ranges do not fix a 3D position, its floor comes
        from the prediction. The filter itself is unchanged (publication only). 0: off.
    few_anchors_floor_p_max : float [-]
        Cap of the published most probable floor's probability with fewer than
        ``min_anchors_tracking`` ranges (the probabilities mixed towards uniform until the
        cap holds; the most probable floor is unchanged).
    max_order : int
        The first-arrival families of at most this many interactions
        (:func:`diffpos.paths.mechanisms.mechanism_set`) beyond the 18 mechanisms are part of
        every link's out-of-model component (:mod:`diffpos.tracking.families`); 2: none.
        Default 3 (with ``family_weight="mechanism"``, ``family_gate="misfit"``,
        ``family_history`` 1, ``family_min_links`` 5, ``family_minority``). History: 3 from 431695e, back to 2 at
        2fd5568 (a link the hypothesis had not seen counted as a misfit, so at a track's start
        every link offered the families to every floor: the 3 s, 4-node, 5-anchor synthetic
        window-edge run of tests/system/test_recorder.py fell from 72.5 to 50.0 % right floor;
        on Sionna RT's three-UAV held-out building the families cost 13 points), 3 again with
        the fit history and the three-range guard (docs/tracking_evidence.md: live replays on
        Sionna's channel paper 76.0 -> 87.2 %, large 90.2 -> 91.6 % with confidently wrong
        0.87 -> 0.22 %, heldout-2 69.4 % both, heldout-1/3 unchanged; the emulator's large and
        paper 99.3-99.6 %; the synthetic run 71.7 %), and back to 2 again after it: live at real
        time on the emulator's ``large`` (20 s) it put 98.7 % of the node-epochs on the right floor
        with 0.78-0.83 % confidently wrong in 7 of 9 runs, where the inputs replayed at 2 give
        99.2 % and 0.34 % (the emulator's bars: 99 % and 0.5 %; docs/tracking_evidence.md), and
        on the 16-anchor soak input it costs +30 % CPU; 3 again with ``family_minority``
        (the cause of that live cost: one walker whose true-floor track started in a wrong
        state, the families taking its misfit links out of its fit; with the rule the same
        inputs give 99.2 % and 0.29 %, docs/tracking_evidence.md "The live-only cost found").
        4 measured no better than 3 on Sionna's paper building (static: 72.85 against 73.13 %
        right floor) for more CPU.
    family_weight : {"mechanism", "outlier"}
        How an extra family explains a link (:func:`diffpos.tracking.families.family_log_weight`):
        ``"mechanism"``, each family as one more candidate mechanism (a mechanism's prior, the
        inlier weight); ``"one"``, the families together as ONE more candidate (their mean
        density at the prior ``1 / (n_18 + 1)``); ``"outlier"`` (before), as half of the
        out-of-model component at the prior outlier weight. Measured (docs/tracking_evidence.md,
        with the fit history and the three-range guard): on Sionna RT's channel "mechanism" >
        "one" > "outlier" (static paper 72.6 / 71.9 / 70.3 % right floor, without families
        69.5 %); on the synthetic window-edge channel (in the path model, no family ever the
        first arrival; 8 seeds, 10 s) the order reverses (44.7 / 53.4 / 61.0 %, without 56.9 %).
    family_gate : {"misfit", "outlier"}
        The links whose extra families are evaluated: ``"misfit"``, those the hypothesis'
        last real update called an outlier or fitted with an NIS above ``nis_limit`` (once it
        has a fit history: ``family_history``; a node with ``family_min_links`` ranges);
        ``"outlier"`` (before), those with a forgotten outlier count above 0.5.
    family_history : int [updates]
        (``family_gate="misfit"``) A link is a misfit of a hypothesis, and offered the
        families, only once that hypothesis has had it in this many real updates (its
        forgotten count ``link_all`` at least that of as many consecutive updates): a fit is
        judged only after there was one. 0 (before): a link the hypothesis has not seen
        counted as a misfit, so at a track's start every link offered the families to every
        floor (the 4-node synthetic window-edge run of tests/system/test_recorder.py: 72.5 %
        right floor at ``max_order`` 2, 50.0 % at 3 with 0, 71.7 % with 1). Default 1: the
        link's first fit is the first evidence of a misfit; counting more than one update
        delays the families of the hypotheses that went dormant (updated once per
        ``dormant_refresh_s``), measured worse on Sionna RT's paper building (live replay:
        74.0 % right floor with 5, 87.2 % with 1, 83.9 % with 0; docs/tracking_evidence.md).
    family_min_links : int
        The families are offered only to a node with at least this many ranges in the epoch.
        Default 4: three ranges are fitted exactly by a position on any floor given any
        mechanism per link, so a family chosen for one of them (after the fact: it is offered
        where the 18 fit badly) is tested by no other range, and the floors are told apart
        only by what the families do not change (heights, existence, SNR); the same count as
        :func:`diffpos.tracking.evidence.model_doubt`'s (the ranges beyond three test the
        floor). Measured: Sionna's three-UAV held-out building, live replay, 69.4 % right
        floor without families, 65.6 % with them from the first fit, 69.4 % with this guard.
        Default 5 (4 before 7103507, 2026-12-06 19:37 UTC): a family offered to one link of four
        leaves three in-model ranges, again fitted exactly on any floor, so four other ranges
        are needed to test it. Measured (docs/tracking_evidence.md "Five ranges"): with 4 the
        emulator's default paper run (``diffpos emulate``, 4 UAVs, in the path model) fell
        from 98.0 to 95.9 % right floor (deterministic over three runs), with 5 it stays 98.0
        %; Sionna's live ``large`` (8 UAVs) 91.5 / 0.30 % (4) and 91.4 / 0.34 % (5) right /
        confidently wrong (90.2 / 0.87 % without families); Sionna's 4-UAV paper building
        loses the families' gain (live 87.8 -> 76.0 %, static 72.1 -> 69.5 %, as without);
        ``family_learned_links`` (default 4) gives it back where the track has learned that
        its channel has out-of-model first arrivals. 0: every node (before).
    family_minority : bool
        The extra families only for a hypothesis whose misfit links (the gate's, above) are
        fewer than half of the node's ranges: a hypothesis that fits most of its ranges badly
        has a wrong state, not several out-of-model links (the tracker's own test of a bad
        epoch, ``2 n_in < n_meas``). Offered the families there, the misfits are explained by
        families at the wrong state and drop out of its position fit; the few ranges left fit
        it exactly, so it cannot re-converge. Default True (False before; measured in
        docs/tracking_evidence.md "The live-only cost found": the emulator's ``large`` live
        inputs that gave 98.7 % right floor and 0.83 % confidently wrong with the families
        give 99.2 % and 0.29 %, as ``max_order`` 2; Sionna's live replays unchanged within
        0.6 points).
    family_first : bool
        An extra family explains a link at a hypothesis only as far as it can be the first
        arrival there: its density is weighted by the probability that none of the 18
        mechanisms shorter than it (by more than 3 range sigmas) was detected, each missed
        with ``Phi((T - S_j) / SNR_SIGMA_DB)`` (``S_j`` its SNR predicted by the emulator's
        amplitude model, ``T`` the link's detector threshold; the tracker's SNR model, used
        only where the link has a measured SNR and a radio model), at least
        ``exp(-snr_cost_cap_nats)`` (the robust SNR likelihood's cap: about the outlier's
        share) (:func:`diffpos.tracking.families.first_arrival_log_prob`). Default False:
        measured (docs/tracking_evidence.md "The first-arrival condition") it mends the
        synthetic window-edge channel (in the path model, no family ever the first arrival;
        8 seeds: 3 s 44.9 -> 50.6 % right floor, 10 s 44.7 -> 56.1 %; ``max_order`` 2: 52.0 /
        56.9 %) but gives back the families' whole gain on Sionna RT's channel (static paper
        72.55 -> 69.91 %, open plan 66.85 -> 63.22 %, ``max_order`` 2 69.53 / 62.68 %; live
        large 91.6 -> 89.9 % with confidently wrong 0.22 -> 1.33 %): there the families
        that help are the ones the emulator's amplitude model rules out (its shorter paths
        are absent or far weaker on the traced channel). Default True from e94ad45 (without
        the cap) to the next commit.
    family_learned_links : int
        (``max_order`` > 2) The extra families are also offered to a node with at least this
        many ranges but fewer than ``family_min_links`` while its track has learned that its
        channel has first arrivals the 18 mechanisms do not explain
        (:func:`diffpos.tracking.evidence.unexplained_log_odds`: the forgotten rate of the node's
        epochs with a redundant range (four or more) in which EVERY hypothesis misfits one of
        the present links at its last real update, a floor-independent sign of an out-of-model
        first arrival, above the rate the path model predicts with its outlier prior and the
        ``nis_limit`` tail, by a Bayes factor against a uniform rate). 0: off. Default 4
        (0 before; docs/tracking_evidence.md "A learned family prior"): four ranges are the
        fewest with one beyond the three that fit a position on any floor, so the fewest at
        which an epoch can be misfit by every hypothesis. Measured (replays scored over ALL
        node-epochs, right floor / confidently wrong): Sionna's live paper building (4 UAVs)
        76.02 -> 88.15 % (0.00 % both; families from four ranges everywhere: 87.78 %), the
        README's main command (``diffpos emulate``, the emulator's channel, 4 UAVs) 97.87 %
        unchanged (no epoch of it is misfit by every hypothesis; families from four ranges
        everywhere: 95.83 %), Sionna's live ``large`` 91.37 / 0.34 -> 91.42 / 0.31 %,
        heldout-1/-2/-3 and the emulator's lockstep and live runs unchanged; static Sionna
        paper 69.53 -> 72.10 %.
    family_snr : bool
        (``max_order`` > 2) Every extra family is scored with its SNR as the 18 mechanisms
        are: its density is weighted by the robust SNR likelihood about the emulator's
        amplitude model for that family (Gaussian, ``SNR_SIGMA_DB``, the cost capped at
        ``snr_cost_cap_nats``; :func:`diffpos.tracking.families.family_snr_log_lik`,
        :func:`diffpos.channel.emulator.pair_family_snr_db`) instead of the outlier's flat
        SNR density ``1 / SNR_SPAN_DB``; a family with no power is no candidate. Only where the
        link has a measured SNR and a radio model. Default False (docs/tracking_evidence.md
        "Families scored with their SNR, the gate's misfit at the fit").
    family_select : bool
        (``max_order`` > 2) The extra families are offered to every link the hypothesis has
        fitted (``family_history``, ``family_min_links`` as for the misfits), not only to its
        misfits, so an exact family competes with the 18 mechanisms in the link's selection
        (a family-explained link is an outlier for the IEKF); ``family_minority`` still
        counts the misfits only. Why: on the emulator at ``channel_max_order`` 4 the true
        floor fits order-3/4 slab-series first arrivals with a wrong one of the 18 inside
        ``nis_limit`` (never a misfit, so never offered the exact family), and that mechanism
        pulls its fit. Default False (docs/channel_mix.md "Session 26": with
        ``family_minority`` off too, emulator order 4 ``large`` 84.9 -> 89.4 % right floor
        and 6.3 -> 2.7 % confidently wrong over 3 seeds, but order-3 paper 98.5 -> 97.0 %).
    family_select_min_links : int [ranges]
        (``max_order`` > 2) A node with at least this many ranges in the epoch gets the
        extra families on every link the hypothesis has fitted (as ``family_select``) and
        without the ``family_minority`` rule; a node with fewer keeps the gate of the other
        settings. 0: off (default). Why: on the emulator at ``channel_max_order`` 3 up to half
        of an 8-UAV node's first arrivals are order-3 slab series (D(lower)-R(ceiling)-R(floor),
        R(ceiling)-R(floor)-R(ceiling)), which the floor below explains with in-model
        mechanisms, while the true floor fits some with a wrong one of the 18 inside
        ``nis_limit`` (never offered the exact family) and calls the rest misfits, so that half
        its ranges misfit and the minority rule closes the families; with many ranges the
        in-model rest still tests the state. With 4 ranges (the paper building's UAVs) a family
        on a well-fitted link leaves three ranges, fitted on any floor (``family_min_links``),
        so those nodes keep the misfit gate and the rule (docs/channel_mix.md "Session 27").
    family_worst_min_links : int [ranges]
        (``max_order`` > 2) A node with at least this many ranges but fewer than
        ``family_min_links`` gets the extra families on ONE link per hypothesis: the present
        link with the largest selection NIS (``link_fit``) among those its last real update
        fitted with one of the 18 (an outlier link is the misfit gate's, not this one's),
        where that NIS is at least ``family_worst_nis`` and the link has a fit history
        (``family_history``); on
        top of the other settings' gate; with ``family_minority`` none to a hypothesis that
        misfits half of the ranges or more (:func:`diffpos.tracking.tracker._worst_link`).
        0: off. Default 4 from session 30 (replays of the session-24/26 recordings with
        today's other defaults, docs/tracking_evidence.md "Session 30, lead"): Sionna RT paper
        ten seeds 89.46 -> 91.31 % right floor (8 seeds up, s2 -4.0 and s6 -3.3), Sionna
        ``large`` x5 93.96 -> 94.06 (no seed down), heldout-1/-2/-3 identical, main command
        99.38 -> 99.42, ``large30`` 99.99, 16 random buildings 99.70 -> 99.61 (rand-7-12
        -0.74, rand-7-4 -0.74), the emulator at ``channel_max_order`` 3 main 97.72 -> 98.51;
        tracker CPU x1.02-1.15. Why (docs/channel_mix.md "Session 29"): on the emulator at
        ``channel_max_order`` 3 a 4-UAV node whose first arrival from one UAV is an order-3
        slab series (D(lower)-R(ceiling)-R(floor)) is fitted at the true floor with a wrong one
        of the 18 inside ``nis_limit`` (capped SNR cost, the fit pulled), while the floor
        above explains all four ranges with in-model mechanisms: ~2.3 nats per update against
        the true floor with its track at the truth (main command seed 6, r03). Offered the
        families on that one link the true floor explains it exactly and leads by ~7 nats;
        one link at most, so three ranges and the track's prior still test the floor (every
        fitted link, ``family_select`` at four ranges, lets two of four leave the fit).
    family_worst_nis : float [-]
        ``family_worst_min_links``' least NIS of the worst in-model link. Default 1
        (measured on the main command at order 3, seeds 0-11, offline: 0 and 2 worse).
    family_worst_outliers : bool
        (``family_worst_min_links``) The ONE link per hypothesis may also be a link its last
        real update called an outlier (``link_fit`` inf), which then counts as its worst (ahead
        of every finite NIS); the fit history and ``family_minority`` as before (so at four
        ranges at most one outlier). Default False. Why (docs/tracking_evidence.md "Session 31:
        the paper building on Sionna"): on Sionna's paper building the true floor of a
        four-range node calls an out-of-model first arrival (e.g. the order-3
        ``R(ground)-R(ceiling)-R(floor)``) an outlier, where its learned outlier weight is
        small because it fitted that link in the model before the first arrival changed; a
        lower floor fits it with one of the 18 and gains ~1 nat per epoch. Below
        ``family_min_links`` the misfit gate offers the outlier no family (unless the track
        learned its channel's out-of-model arrivals, which a floor explaining every range
        prevents), so the exact family never reaches the true floor.
    family_worst_outliers_settled : bool
        (``family_worst_outliers``) Only at nodes whose floor was not contested within
        ``floor_contest_s`` (``TrackerState.lead_ns``: the most probable floor unchanged, with a
        majority and at least four ranges): a hypothesis of a node in doubt (start-up, a floor
        change on the stairs) calls a link an outlier because its state is wrong, and the
        family then takes that range out of its fit on any floor. Default False.
    family_fit : {"prior", "residual"}
        What the family gate's misfit (``family_gate="misfit"``, ``TrackerState.link_fit``)
        of a link is: ``"prior"``, its selection NIS at the prior covariance; ``"residual"``,
        its fitted residual over the range noise, ``res^2 / var`` at the updated state (a
        drifted track whose fit absorbs a range no longer calls it a 3-sigma miss by the
        prior's spread alone). Default "prior" (the same section).
    floor_model_doubt : bool
        The published floor probabilities are mixed towards uniform by the probability that
        the node's data hold a first arrival the path model does not explain, by the learned
        outlier weights of the most probable hypothesis' links
        (:func:`diffpos.tracking.evidence.model_doubt`; needs ``link_learn``). Publication
        only. False: not mixed (before).
    floor_robust_links : int
        In the published odds of the most probable floor against every other one, the share
        of that floor's deficit carried by its this many most decisive links is worth at most
        ``ln((1 - outlier_weight) / outlier_weight)`` (:func:`robust_floor_log_prob`; needs
        ``link_learn``). Publication only. Default 0 (off): measured with 1
        (docs/tracking_evidence.md, with ``floor_model_doubt``) the wrong floors published
        at p >= 0.95 on Sionna RT fall from 2.19 to 1.81 % (paper), 2.44 to 1.85 % (open
        plan), 1.43 to 0.45 % (a held-out building), but the emulator's floors, 99.6-99.7 %
        right, are then published underconfident (``large``: 20 % of its node-epochs at
        0.5-0.8, 99 % right; floor log score 0.020 -> 0.087 nats, ``default`` 0.074 -> 0.200).
    floor_contest_s : float [s]
        The published floor probabilities of a node whose most probable floor was *contested*
        less than this long ago are tempered by ``floor_contest_kappa`` instead of ``kappa``
        (:func:`evidence_temper`; :func:`published_floor_probabilities`' ``contested``).
        Contested (:func:`floor_contested`, the tracker's ``lead_floor`` / ``lead_ns``): in an
        update in which the most probable floor changed, or its filter probability was below
        1/2, or the node had fewer than four ranges (three ranges fit a position on any floor:
        the ranges did not test the floor in that epoch). Why: ``kappa`` (3.9, the AR(1) factor
        of the lag-1 correlation) holds where the filter's floor log-odds are the jump floor
        plus the latest few epochs' evidence (a lead held for long); after a contest the lead
        is the sum of every epoch's evidence since, whose correlation is ~0 only after ~3 s
        (the measurement of ``floor_evidence_lag1_corr``), so its information is that of
        ``n / (1 + 2 sum_k rho_k)`` epochs, 10 over the measured curve. Publication only: the
        filter, the chosen floor and the position are unchanged. Default 3 s (since
        2026-12-07; 0: off, as before). Measured (docs/floor_calibration.md "Session 25",
        replays of unbounded lockstep recordings): with 3 s and 10, the wrong floors
        published at p >= 0.95 on the README's main command (seeds 0-11) fall from 1.06 to 0.09
        % of the node-epochs (worst seed 3.70 -> 0.46 %), Sionna RT's live ``large`` 1.06 ->
        0.26 %, its three-UAV heldout-2 2.85 -> 0 % (right floor identical by construction);
        the price: fewer node-epochs published at >= 0.95 (main command 70.0 -> 61.7 %,
        Sionna ``large`` 80.1 -> 73.7 %), those then right 99.65-100 % where four or more
        UAVs range.
    floor_contest_kappa : float [-]
        The tempering divisor of the published floor log-odds within ``floor_contest_s`` of a
        contest (default 10: ``1 + 2 sum_k rho_k`` over the measured correlation curve of the
        floor evidence, the figure of ``floor_evidence_lag1_corr``'s docstring).
    floor_contest_vertical : bool
        A node whose most probable floor's vertical (stairs) mode is more probable than its
        level mode is *contested* too (:func:`floor_contested`), so its floor is published with
        ``floor_contest_kappa`` while on the stairs and ``floor_contest_s`` after. Why: in the
        level mode the height prior (nominal height +- ``height_sigma_m``) is itself floor
        evidence (the ranges' height must match one floor's nominal height); in the vertical
        mode the height is free within the band, so the lead built under the level mode is no
        longer tested by it, and on the stairs the floor is what is changing. Publication only
        (the clock ``lead_ns`` feeds the publication alone). Default False (off: as before).
        Measured (docs/floor_calibration.md "Session 26", with ``floor_band_bound``): wrong
        floors at p >= 0.95 on 16 random emulator buildings 0.13 % (worst 0.83 %) -> 0.03 %
        (worst 0.28 %), main command 0.09 -> 0.06 %, Sionna RT ``large`` 0.26 -> 0.19 %; the
        price: 1-7 points fewer node-epochs published at >= 0.95 (log score +0.002-0.015).
    cov_published_floors : {"off", "all", "credible"}
        Which floor weights the published covariance's spread of the hypotheses' means about
        the published point uses (:func:`floor_reweighted`, :func:`mixture_mse_cov`; each
        floor's two modes keep their ratio). "off": the untempered filter probabilities (as
        before; they put ~1e-6 on a floor the published vector gives 0.1-0.3). "all": every
        floor's PUBLISHED probability (tempered, model doubt, few-anchors cap, band bound:
        what the estimate says). "credible": the published probability for the floors of the
        published 95 % credible set (the most probable floors until their mass reaches the
        0.95 of the 95 % ellipsoid: :func:`credible_floor_weights`), the filter's for the
        others (a floor outside the set is outside the 95 % region, and its moment would only
        widen the ellipsoid of the floor the node is on). Why: on Sionna RT the wrong-floor
        node-epochs (5-14 %) were almost all outside the 95 % ellipsoid (2-10 % covered): the
        truth's floor hypothesis sits 1.5-2.5 m away in height AND horizontally, and the
        untempered weight makes that spread vanish. Publication only (position, floor,
        probabilities, status unchanged). Default "credible" (from session 28; "off" before:
        coverage on Sionna paper 85 -> 95 %, the 3-UAV building 76 -> 91 %, ``large`` 90 ->
        96 %, the main command 93 -> 96 %; docs/tracking_evidence.md "Session 28: the 95 %
        ellipsoid's coverage").
    cov_few_floors : {"off", "temper", "model"}
        (with ``cov_published_floors`` "all" / "credible") The floor weights of the published
        covariance's spread at a node whose floor the families' SNR tested this epoch
        (``min_anchors_tracking`` <= ranges <= ``family_few_links``) and whose floor was not
        contested by the floors themselves (the same lead as the previous update, with the
        majority: :func:`floor_contested` at four ranges). Why: such a node is contested
        by its range count alone ("three ranges fit a position on any floor, so the ranges did
        not test the floor"), so its published log-odds are divided by ``floor_contest_kappa``
        every epoch, and its family-explained link counts as an outlier in the learned arrays,
        so the model doubt mixes its floors towards uniform; both premises are false where the
        families' SNR tested the floor, and the credible floors' spread then spans a storey
        at nearly every epoch (Sionna heldout-2: published best floor 0.58 on average at
        97 % right). "temper": the weights are the published probabilities with the evidence
        temper (:func:`evidence_temper`) instead of the contest's (model doubt, band bound
        kept); "model": also without the model doubt's uniform share. The floor
        probabilities, floor and position are published as before (publication of the
        covariance only). Default "temper" (since 2026-12-08, with the two settings above);
        "off": as before. Measured (replays, today's default +
        ``family_few_links`` 3 + ``family_fit_links`` 3): Sionna heldout-2's 95 % ellipsoid
        98.1-99.7 % -> 90.7-93.6 % with "temper" (88.7-91.4 % with "model"), the random
        building rand-7-13 99.81 -> 97.31 %, every other set identical;
        docs/tracking_evidence.md "Session 32".
    floor_band_bound : bool
        The published probability of the published floor is at most the mass that the
        published height ``N(z, P_zz)`` (the estimate's own position and covariance) puts on
        that floor's height band ``[floor, floor + floor_height_m)`` of the building (the
        lowest band extended below, the highest above: the node is in the building), and at
        least 1/2 (so it stays the most probable); the mass taken off goes to the other floors
        in proportion to their band masses (:func:`height_band_bound`). Why: a node on the
        stairs whose height straddles a slab is on either floor; the filter's floor
        hypotheses each keep their height inside their own floor's box, so their odds say
        which box fits, not on which side of the slab the node is, and a lead held from the
        floor before is published at >= 0.95 while the height is within centimetres of the
        boundary. Publication only: the filter, the chosen floor, the position, covariance and
        status are unchanged. Default False (off: as before). Measured (docs/floor_calibration.md
        "Session 26"): the 16 random buildings' rand-7-2 0.56 -> 0.37 % wrong at p >= 0.95, at
        most 1 point fewer node-epochs at >= 0.95 on any set, log score unchanged (+-0.001).
    mode_search_outliers : int
        Other modes of a hypothesis' posterior: an updated hypothesis that calls at least
        this many of its ranges outliers is also fitted from the best cells of a local grid
        around its prediction, and each such fit is scored under the hypothesis' own prior in
        closed form (:func:`diffpos.tracking.tracker._mode_pairs`): the better mode is kept
        (max-mixture). What a first-arrival switch to a path that exists a few decimetres
        from the prediction needs (docs/tracking_evidence.md "Session 23: other modes of a
        hypothesis at a first-arrival switch"). 0 (default): off (before).
    mode_jump_rate_hz : float [1/s]
        With ``mode_search_outliers``: the rate of a *jump* of a hypothesis' state, its
        prior the mixture ``(1 - e) N(x, P) + e N(x, P + J)``, ``e = min(rate dt, 0.5)``, ``J``
        the jump covariance (``mode_jump_sigma_m``): the candidates are also scored under
        ``N(x, P + J)`` with the weight ``e``. 0 (default): no jump component.
    mode_jump_sigma_m : float [m]
        Standard deviation per position axis of ``J``; also the reach of the mode search
        (its grid covers 3 standard deviations of ``P + J``).
    mode_search_max : int
        With ``mode_search_outliers``: only a node's this many most probable hypotheses (by
        their predicted probability) are searched (the CPU of the search bounded where many
        hypotheses misfit a link: ``large``'s 8 anchors); 0 (default): every one.
    mode_search_min_links : int
        With ``mode_search_outliers``: only hypotheses of nodes with at least this many ranges
        are searched. With three ranges a position fits them exactly on any floor, so a
        search there finds every floor's best fit again (the argument of
        ``family_min_links``); 0: ``min_ranges_init``.
    reseed_min_links : int
        With ``reseed_max``: only hypotheses of nodes with at least this many ranges this
        epoch are re-seeded from a snapshot of their floor. With three ranges a snapshot fits
        them on any floor (the argument of ``family_min_links``), so a re-seed there hands a
        wrong floor an exact fit; with four or more one range is redundant and the floor's
        snapshot is tested by it. Default 4 (since 2026-12-07, with ``reseed_max`` 2); 0:
        ``min_ranges_init`` (before). Measured on
        Sionna RT's live paper building (docs/tracking_evidence.md "Session 24: where Sionna
        paper's misses are").
    reseed_period_s : float [s]
        With ``reseed_max``: each hypothesis of a node is re-seeded at most once per this
        period of measurement time, in the epoch that crosses one of its boundaries ``origin +
        k T - h T / H`` (hypothesis ``h`` of ``H``; the phases and the node's origin of the
        dormant refresh, :func:`diffpos.tracking.tracker._refresh_due`): a hypothesis that
        qualifies (``reseed_epochs`` bad updates) between its boundaries waits for the next
        one (still bad then: re-seeded; a good update clears it). A node's re-seeds are
        spread over the period and their rate is bounded (with ``T`` = 1 s at 10 Hz at most
        one of a node's 10 hypotheses is at a boundary per epoch), so the snapshot work of a
        fusion step is bounded by its nodes whatever they qualify for at once; a function of
        the node's own inputs (rows stay independent). Measured on the live ``large`` (docs/
        performance.md "Session 26"): a re-seed is ~0.6 ms CPU, 3.4 per 50-node step on
        average (up to 8), 13 % of a step; 99 % of them renew a floor below 1e-3 probability,
        an awake one every third epoch. 0 (default): any epoch it qualifies in (before).
    reseed_starts : int
        With ``reseed_max``: the grid's best cells a re-seed's snapshot of the floor fits
        (each by two measurement updates, the best fit kept); 0 (default): ``init_starts``
        (before). 1: the best cell only, as the deficit test's snapshot (issue 37: a re-seed
        is ~15 % of the tracker's CPU on the emulator's ``large``, its updates ~2/3 of that;
        99 % of re-seeds renew a floor below 1e-3 probability).
    mode_search_new_misfit : float [fraction of a link's real updates]
        With ``mode_search_outliers``: only the outliers of links the hypothesis has fitted
        lately count towards ``mode_search_outliers``: the link's forgotten outlier rate for
        the hypothesis before this update (``link_out / link_all``, forgetting
        ``link_forget`` per real update; needs ``link_learn``) must be below this value (a
        first-arrival switch; :func:`diffpos.tracking.tracker._new_misfit`). A link out of
        the hypothesis' model all along (Sionna RT's persistent out-of-model first arrivals,
        or a wrong floor's misfit) does not start a search. With ``link_forget`` 0.95 a
        link fitted for long reaches a rate of 0.5 after 14 consecutive outlier updates.
        0 (default): every outlier counts (before).
    deficit_nats : float [nats]
        Re-seed on an *evidence deficit* (issue 34 item 3; docs/tracking_evidence.md
        "Session 25"): a floor's hypothesis whose prior sits in the wrong place on its floor
        while fitting its ranges well enough (NIS below ``nis_limit``: the NIS re-seed never
        fires) is tested against a fresh snapshot of its floor
        (:func:`diffpos.tracking.model.snapshot`, the current ranges): ``D = log Z(s, P) -
        log Z(x, P)``, the log marginal likelihood of the epoch's ranges under the
        hypothesis' own prior spread ``P`` centred at the snapshot's position ``s`` against
        centred at its own prediction ``x`` (the same measurement update: the same Occam
        factor, learned link weights, mechanism model and family gate). Under a track at the
        truth ``2 D`` is about chi-square with 2 degrees of freedom (the snapshot fits the
        horizontal position), so ``P(D > t) = exp(-t)``: 4.6 nats is the 1 % level. A
        hypothesis whose ``D`` exceeds this value in ``deficit_tests`` consecutive tests is
        re-seeded from the snapshot by the NIS re-seed's path (its floor probability kept;
        ``reseed_max`` per node and epoch, ``reseed_min_links``; needs ``reseed_max`` > 0).
        Only TRACKING nodes with at least ``reseed_min_links`` (and ``min_ranges_init``)
        ranges are tested. 0 (default): off (before).
    deficit_tests : int
        With ``deficit_nats``: consecutive tests of a hypothesis above the threshold before
        its re-seed (a test of the floor in which ``D`` is below resets the count).
    deficit_period_s : float [s]
        With ``deficit_nats``: every floor of a node is tested once per this period (floor
        ``f`` at phase ``f / F`` of it, measurement time since the node's initialisation, so
        a replay tests at the same epochs and the rows stay independent); a test is one
        snapshot of that floor and two measurement updates per mode (the bounded work: about
        ``F / (period x rate)`` floors per node-epoch, 0.5 at 10 Hz with 5 floors and 1 s).
    deficit_level_only : bool
        With ``deficit_nats``: test (and so re-seed) only a floor's level mode. The snapshot
        is the level model's fit (at the nominal height), so it is the candidate of the level
        mode; a vertical (stairs) mode re-seeded from it on a rival floor handed a stairs
        walker's wrong floor the win on Sionna RT's paper building (docs/tracking_evidence.md
        "Session 25"). False (default): both modes.
    deficit_exact : bool
        With ``deficit_nats``: every due floor tested in full, its snapshot from
        ``init_starts`` grid cells, a dormant mode updated for the test (session 25's first
        version). False (default): the cheaper test. A floor is due at its level
        hypothesis' refresh phase (so with ``dormant_refresh_s`` = ``deficit_period_s`` its
        dormant level mode is refreshed that epoch), only the modes updated this epoch are
        tested, and a mode is snapshot only where a pre-check from its own update exceeds
        ``deficit_nats`` (``(q + c) / 2 + n_out log(outlier_span_m / outlier_weight)``: the
        prior term and the fitted links' chi-square of its fit, and an outlier's cost per
        link it calls an outlier; for the same mechanisms, linearised, ``D`` cannot exceed
        it), from the grid's best cell only; a floor below ``1e-3`` with no deficit
        counted is tested every ``deficit_quiet_every`` periods. The tests' CPU on the
        emulator's ``large30`` 0.34-0.39 -> 0.11 ms per node-epoch (docs/tracking_evidence.md
        "Session 25: a cheaper deficit test").
    deficit_quiet_every : int
        With ``deficit_nats`` and not ``deficit_exact``: a floor whose probability is below
        ``1e-3`` and whose modes have no deficit counted is tested once every this many
        ``deficit_period_s`` (2, default: at the second of its boundaries; 4 measured
        +12 % instead of +23 % CPU on ``large30`` and gave back Sionna ``large``'s gain,
        docs/tracking_evidence.md "Session 25: a cheaper deficit test"; 1: every period).
    first_arrival_prior : float
        Weight ``w`` (0-1) of the detector's skipped paths in a candidate mechanism's prior
        (:func:`diffpos.tracking.model.skip_cost`): a mechanism is the reported first arrival
        only if every candidate arriving before it was below the detector's threshold, so its
        uniform prior is multiplied by ``w prod_j Phi((T - S_j) / sigma) + 1 - w`` (``S_j``
        the earlier candidates' predicted SNRs, ``T`` the threshold, at least the measured
        first arrival's SNR less ``fap_threshold_db``). 0: off, the uniform prior. ``1 - w``
        bounds what a model that predicts a path too strong can cost a link (``-log(1 -
        w)``: 1.6 nats at 0.8). 0.8 (default since 2026-12-07; 0.8 / 0.9 / 0.97 measured:
        0.9 and 0.97 published a wrong floor at p >= 0.95 on 0.65 / 1.30 % of one main
        command seed's node-epochs): the main command's seeds 0-11 91.1 -> 96.6 % right
        floor, Sionna RT's live paper / `large` / 3-UAV building 87.3 / 90.9 / 61.0 -> 91.6 /
        93.4 / 75.2 % (five seeds), 16 random buildings 98.7 -> 99.6 %, docs/tracking_evidence.md
        "Session 26: the detector's skipped paths".
    edge_retry_margin_m : float [m]
        A level-mode hypothesis in good standing (at least four ranges, every present link's
        learned outlier probability below ``edge_retry_eps``) that calls a present link an
        outlier in an update is updated again with every existence margin at least this wide,
        and that update replaces the first (:func:`diffpos.tracking.tracker._edge_retry`): a
        mechanism the track has been fitting is not declared gone because the prediction
        stepped a decimetre or two over its existence edge (a level track's margin is the
        fixed ``exist_margin_m``; the vertical mode's follows its own height uncertainty). The
        README main command's top-floor walker r05 walks on the edge of the outer UAVs' slot
        15 (docs/tracking_evidence.md "Session 26: a wider margin at an existence edge"). 0:
        off; 0.4 (default since session 27, with ``edge_retry_node``). Measured with 0.4 (offline reruns, five / twelve seeds): main command
        96.64 -> 98.54 % right floor, Sionna RT's live paper building 91.56 -> 90.98 %; with
        the vertical mode retried too 88.96 %.
    edge_retry_eps : float [-]
        With ``edge_retry_margin_m``: the good-standing bound of a link's learned outlier
        probability (the learned weights do not go below ``outlier_weight``, 0.02).
    mechanism_prior_min_links : int
        A link's inlier prior is uniform over its candidate mechanisms, ``(1 - eps) / n_cand``
        (:func:`diffpos.tracking.model.select`), only for nodes with at least this many
        ranges in the update; a node with fewer gives every candidate the link's inlier
        weight ``1 - eps`` (no ``-log n_cand``; :func:`diffpos.tracking.model.few_links_weights`).
        Why: the count is the Occam factor of a coincidence (a hypothesis with more
        mechanisms fits a redundant range by chance more often), which needs a redundant
        range: with three ranges (three position coordinates) every floor's hypothesis fits
        them by some combination of mechanisms, and the max-mixture then keeps the ``1 /
        n_cand`` of the one combination it fitted without the others' solutions elsewhere on
        the floor, so the count is a fixed preference for the floors with fewer mechanisms
        (the floor level with the UAVs: direct paths), repeated every epoch. On Sionna RT's
        3-UAV building it handed the floor of the low UAVs 2.6 nats per epoch from a
        ceiling-bounce truth (docs/tracking_evidence.md "Session 27: the 3-UAV building").
        0: every node (before session 27); 4 (default, with ``mechanism_switch_p`` 0.3):
        nodes with three ranges or fewer. Measured
        with 4 (replays, today's default otherwise): Sionna RT heldout-2 75.08 -> 86.70 %
        (five seeds, every seed better), its emulator version 98.27 -> 98.67 % (three seeds),
        16 random buildings 99.65 -> 99.67 %, Sionna ``large`` 93.35 -> 92.68 % (every seed
        worse: 8.7 % of its node-epochs have fewer than four ranges); inputs where every
        node-epoch has four ranges or more are identical.
    edge_retry_prior : bool
        With ``edge_retry_margin_m``: a pair's retry replaces its first update only where
        every link it re-fits (an outlier in the first update, a mechanism in the retry) is
        fitted with a mechanism that is a candidate at the pair's prior (clamped into its
        floor's box) with the ordinary existence margin, the first update's own first-pass
        test (:func:`diffpos.tracking.tracker._refits_at_prior`): the retry then only undoes
        a later selection pass that dropped a mechanism existing where the track predicted
        it (the fit moved over its edge); a mechanism that exists only with the wider margin
        is not the one the track has been fitting. On Sionna RT's live paper building most
        re-fits the retry makes are of that kind, on a wrong floor's hypothesis
        (docs/tracking_evidence.md "Session 27"). Measured with 0.4 (replays): main command
        98.60 -> 98.06 % right floor (the default 96.69), Sionna paper seeds 0-4 / 5-9
        90.89 / 86.85 -> 90.93 / 87.35 (the default 91.48 / 87.63). False (default): every
        retry replaces.
    edge_retry_node : bool
        With ``edge_retry_margin_m``: when a pair of a node qualifies for the retry, every
        level pair of that node in the same update (every floor's level hypothesis that is
        awake) is updated again with the wider margin and replaced, so the node's floors are
        compared under one existence model: the plain retry widens the margin only for the
        hypotheses that misfit a link, and on Sionna RT's live paper building most of those
        it re-fits are a wrong floor's (docs/tracking_evidence.md "Session 27"). Measured with
        0.4 (replays): main command 98.60 -> 98.65 % right floor (the default 96.69), Sionna
        paper seeds 0-4 / 5-9 90.89 / 86.85 -> 90.20 / 88.72 (the default 91.48 / 87.63; a
        wrong floor at p >= 0.95 on 0.37 % of seed 0's node-epochs). True (default since
        session 27); False: only
        the qualifying pairs.
    mechanism_switch_p : float [-]
        With ``mechanism_prior_min_links`` > 0: instead of the flat prior, a node with fewer
        ranges than that gets a persistent mechanism prior (0: off, the flat prior; 0.3 the
        default since session 27): a link
        whose candidate is the mechanism the hypothesis chose for it at its previous update
        gets the inlier weight ``(1 - eps) (1 - q)``, every other candidate ``(1 - eps) q /
        (n_cand - 1)``; with no previous choice (new link, outlier, the mechanism gone) today's
        ``(1 - eps) / n_cand``. The prior enters the selection (argmax and mixture;
        :func:`diffpos.tracking.model.select_persistent`, compiled in
        ``select_best_kernel``). Why: ``1 / n_cand`` is the prior of a coincidence; a mechanism kept from the previous epoch by a node that barely
        moved is the same coincidence, already paid for, so without a redundant range the
        per-epoch count is a repeated constant (the 3-UAV building: mechanisms kept in 94-95 %
        of link-epochs), while a switch is a new coincidence whose count is owed (Sionna
        ``large``'s few-range nodes: 16-22 % switch; the flat prior lost them).
        Offline (docs/tracking_evidence.md "Session 27: why mechanism_prior_min_links loses"):
        q 0.1-0.5 with the gate 4 keep heldout-2's gain and remove ``large``'s loss.
    link_eps_node : bool
        (``link_learn``) Every hypothesis of a node uses, for each of its links, the node's
        learned outlier weight: the largest ``eps`` any of the node's hypotheses learned for
        that link (:func:`diffpos.tracking.evidence.node_weights`; the inlier weight ``log(1 -
        eps)`` and the outlier component's ``log eps`` both). The counts are still learned per
        hypothesis. Why: whether a link's first arrival is out of the path model is a property
        of the channel between the anchor and the node, not of a hypothesis; learned per
        hypothesis, the weight rewards a hypothesis for having called the link an outlier
        before, so a wrong floor that has tracked for a while pays less for the links it does
        not explain than the true floor does (Sionna RT paper, the wrong node-epochs after 5 s
        with the true floor's track within 0.5 m: the per-hypothesis weights moved the epoch's
        evidence 1.5 nats (median) towards the winner; docs/tracking_evidence.md "Session 28:
        the learned outlier weight"). Default False (per hypothesis, as before).
    link_eps_node_awake : bool
        With ``link_eps_node``: the largest weight over the node's awake hypotheses only (a
        dormant hypothesis is not updated, its counts are those of an old state); a node with
        none awake: over all. Default False.
    link_eps_posterior : int
        (``link_learn``) At a node with at least this many present ranges (0: off), every
        hypothesis' outlier component of a link uses the larger of its own learned outlier
        weight ``eps_h`` and the node's posterior mean ``sum_k p_k eps_k`` over all its
        hypotheses (``p_k``: their probabilities before this epoch's evidence;
        :func:`diffpos.tracking.evidence.posterior_weights`); the inlier weight stays the
        hypothesis' own ``log(1 - eps_h)``. The model-averaged probability that the link's
        first arrival is out of the path model: a floor the node does not believe gets the
        outlier weight the believed floor learned, while a hypothesis with no probability
        lends none (``link_eps_node``'s largest weight came from such hypotheses in 99 % of
        the links it raised, most calling every link an outlier, which made every outlier
        cheap on every floor). With three ranges a position fits every link, so no outlier
        call tells the channel apart (the 3-UAV building lost 5 points on one seed without
        the count); 4 is the redundancy rule of ``reseed_min_links``
        (docs/tracking_evidence.md "Session 29: the model-averaged outlier weight"). Default
        0 (per hypothesis, as before).
    link_eps_lend_contest_s : float [s]
        With ``link_eps_posterior``: a node lends its model-averaged outlier weight only while
        its floor is in doubt, i.e. within this many seconds of its last contested update
        (``TrackerState.lead_ns``: the most probable floor changed, had no majority, or the node
        had fewer than four ranges; :func:`floor_contested`); 0: always (as before). Why: the
        mean cannot tell whether the believed floor is the true one. On Sionna RT paper the
        believed floor is often the wrong one and lending its weight lets the true floor pay
        the same for the out-of-model arrivals both call outliers; on Sionna ``large`` a true
        floor believed for seconds lent its weight to a wrong floor, which then won
        (docs/tracking_evidence.md "Session 29" and "Session 30: lending the outlier weight
        only while the floor is in doubt"). A belief held that long keeps its own learned
        history. Measured with 3 s (replays): Sionna paper ten seeds 89.46 -> 89.92 % (seeds
        -9.0 to +4.3), ``large`` 93.96 -> 93.85 (s1 -0.65): no better than lending always; a
        measured negative. Default 0.
    link_eps_lend_below_p : float [-]
        With ``link_eps_posterior``: a node lends its model-averaged outlier weight only while
        the floor it would publish from its state before the epoch (the most probable floor's
        published probability: one-link-out robust, tempered, with the model doubt;
        :func:`published_floor_probabilities`) is below this probability; 0: always (as
        before). Why: the published probability is the tracker's calibrated belief; on the
        session 26/27 captures (today's default; Sionna paper s0u, s3, s8, ``large`` s0u)
        78-86 % of the wrong node-epochs are published below 0.5, only 5-23 % of the right
        ones, so a belief published with confidence keeps its own learned history. Measured
        with 0.5 (replays): Sionna paper ten seeds 89.46 -> 90.53 %, ``large`` 93.96 -> 93.72
        (s1 -0.65, s3 -0.45): better than lending always (90.77 / 93.52) but still a loss on
        ``large`` (docs/tracking_evidence.md "Session 30"). Default 0.
    link_eps_lend_fewer : bool
        With ``link_eps_posterior``: only the hypotheses that have learned fewer of the node's
        present links as outliers (learned ``eps`` above
        :data:`diffpos.tracking.evidence.LEND_OUTLIER_EPS`) than the node's most probable
        hypothesis borrow its model-averaged weight
        (:func:`diffpos.tracking.evidence.fewer_outliers`): a floor that explains more of the
        links than the believed one is not charged for its shorter history of outlier calls;
        one that needs as many outliers or more keeps its own weight. Measured (replays, with
        and without the 3 s window): Sionna paper ten seeds 89.67 / 89.93 %, ``large`` 93.48 /
        93.56 (the default 89.46 / 93.96): a measured negative. Default False.
    reseed_outliers : int
        A burst of outliers on the believed floor (with ``reseed_max``): a hypothesis of the
        node's believed floor (its probability after this epoch's evidence above 1/2: a
        burst that already moved the belief to another floor is left to count as evidence of
        a floor change; either mode) that is in
        good standing (at least ``reseed_min_links`` and four ranges, every present link's
        learned outlier probability below ``edge_retry_eps``: it has been fitting every link)
        and calls at least this many present links outliers in this epoch's update, among the
        links it has updated with before (``TrackerState.link_slot``, kept with the setting),
        but not most of its present links (then the data jumped and every floor fits badly:
        the ordinary count of bad epochs re-seeds them all, and the believed floor alone
        first would let the others' stale tracks lead),
        is re-seeded from its floor's snapshot in the same epoch (as if it had been bad for
        ``reseed_epochs`` epochs; its log-probability untouched;
        :func:`diffpos.tracking.tracker._outlier_burst`). Why: a
        walker's turn makes the level track overshoot by 1-2 m along its old heading (the
        ranges of four low UAVs barely see it) until the first arrivals switch to a narrow
        mechanism that does not exist at the overshot mean; two outliers cost the true floor
        10-20 nats in one or two epochs, a mirror floor takes the lead and the true floor's
        tracks go dormant metres off, never re-seeded (two outliers of four are not "most":
        the ordinary rule never counts them bad). 2 (default from session 28; 0: off,
        before): the main command's twelve seeds 98.65 -> 99.38 %, Sionna paper and the 3-UAV building
        identical, Sionna ``large`` 93.82 -> 93.85, the random buildings 99.73 -> 99.72
        (99.76 without the most-outliers exclusion; docs/tracking_evidence.md "Session 28: a
        burst of outliers on the believed floor" and "Session 28, lead").
    snr_diffraction_slack_db : float [dB]
        Upward slack of a diffraction slot's SNR likelihood
        (:func:`diffpos.tracking.model.diffraction_slack`): a measured SNR up to this much
        above the slot's predicted SNR costs nothing (beyond it the Gaussian of
        ``SNR_SIGMA_DB`` from the prediction plus the slack; below the prediction as before),
        the density normalised (``+log(1 + slack / (sigma sqrt(2 pi)))`` nats on every scored
        diffraction slot). Why: the amplitude model's horizontal window edges are the
        emulator's perfectly conducting half-plane, too weak deep in the edge's shadow
        against an independent ray tracer (Sionna RT: ``Tx-D(lower)-Rx`` first arrivals a
        median 6-8 dB stronger than predicted where the model's diffraction loss exceeds
        ~40 dB, +-1 dB below ~30 dB); with three ranges every floor fits the ranges and the
        SNR decides, so that bias favours the floors less deep in the shadow every epoch.
        0: off. Default 6 dB (with ``snr_slack_max_links`` 3) since session 29: the
        measured median excess of Sionna's deep-shadow edge diffraction over the half-plane
        (6.0 dB beyond 40 dB loss on the 3-UAV building, 4.3-5.9 dB on the paper building;
        also the best of 3 / 4 / 6 / 8 dB offline on the 3-UAV building's floor accuracy).
    snr_slack_max_links : int
        With ``snr_diffraction_slack_db``: only nodes with at most this many ranges in the
        update get the slack (0: every node; default 3). Measured
        (docs/tracking_evidence.md "Session 29"): the slack on every node costs Sionna paper and the emulator's main command
        (four ranges and more: the range geometry separates the floors and the SNR's bias is
        outvoted, but a slack forgives the wrong floors' too-weak diffractions).
    snr_slack_skip : bool
        With ``snr_diffraction_slack_db``: the detector's skipped paths
        (``first_arrival_prior``) read every slacked diffraction slot's power at the mean of
        the slack's flat top (prediction + half the slack,
        :func:`diffpos.tracking.model.slack_skip_pred`), so the two SNR terms assume the same
        edge. Default False (the half-plane's prediction there, as before).
    snr_edge_model : {"halfplane", "wedge"}
        The window edge of the SNR term's predictions
        (:func:`diffpos.channel.edge_snr.with_wedge_edges`): ``"halfplane"``
        (default) the emulator's perfectly conducting half-plane; ``"wedge"`` the window edge
        as Sionna RT traces it (:mod:`diffpos.channel.wedge`: a thin sheet of the walls' ITU
        material, Sionna RT 2.2's reflection weighting; its window-edge slots 7-13 equal
        Sionna's traced path gains to < 0.02 dB, ``benchmarks/bench_wedge.py``), the physics
        that ``snr_diffraction_slack_db`` stands in for. Only the compiled SNR term
        (:func:`diffpos.tracking.model.snr_term`, the tracker's) uses it; the numpy
        references keep the half-plane. A recording made by the emulator's channel has the
        half-plane's SNRs: measured in docs/channel_mix.md "Session 30".
    skip_threshold_order : int [interactions]
        The detector's threshold that the skipped-path term (``first_arrival_prior``,
        :func:`diffpos.tracking.model.skip_cost`) reads is raised to the strongest path of
        the closed-form first-arrival families of at most this many interactions beyond the
        18 (``mechanism_set(order, partitions=True)``, their SNR by the emulator's amplitude
        model, :func:`diffpos.channel.emulator.pair_family_snr_db`) less
        ``fap_threshold_db``, where that is higher than the 18's
        (:func:`diffpos.tracking.model.family_threshold`). 0 (default) or <= 2: off, the 18
        alone. Why: the detector's threshold is set by the STRONGEST path, and on a channel
        we did not write the strongest is often a higher-order slab series the 18 leave out.
        On Sionna RT's 3-UAV random building (heldout-2) the stairs walker r03 at the start
        (floor 2, static, 3-10 s at every seed, ~70 % of the building's wrong node-epochs)
        gets its UAV2 range as ``Tx-D(lower)-R(ceiling)-R(floor)-Rx`` (7.7-14 dB) behind the
        strongest path ``Tx-R(ceiling)-R(floor)-R(ceiling)-Rx`` at 19.0 dB (the families'
        amplitude model: 19.4 / 7.4 dB): the detector's threshold is ~4 dB and the shorter
        edge paths (-3..+1 dB traced, -7..-1 dB predicted) were below it; with the 18 alone
        the model's strongest there is -1 dB, its threshold the measured first arrival less
        15 dB, and the true floor pays the skip term's cap (1.6 nats) every epoch while the
        floor above (its edge paths deeper in the shadow) pays 0.4
        (docs/tracking_evidence.md "Session 30"). Raising a threshold only lowers skip
        costs (a path below a higher threshold is more probably missed). The SNR term's own
        threshold test is unchanged. Measured (replays, today's default + 3): Sionna
        heldout-2 91.37 -> 92.09 % but seed 4 -1.58, Sionna ``large`` s2 -0.69 / s4 -0.23,
        and nothing on top of ``family_few_links``: not recommended.
    skip_threshold_max_links : int [ranges]
        ``skip_threshold_order`` only at nodes with at most this many ranges in the epoch
        (0: every node) and at least ``min_anchors_tracking``. Default 3 (with three ranges
        every floor fits the ranges and the SNR and skip terms decide alone,
        ``snr_slack_max_links``' argument).
    family_few_links : int [ranges]
        (``max_order`` > 2) A node with at most this many ranges gets the extra families on
        every link its hypothesis has fitted (``family_history``; as ``family_select``, no
        ``family_minority`` rule), each family scored with its SNR (as ``family_snr``, at
        these nodes only; :func:`diffpos.tracking.families.family_log_weight`). 0: off
        (default). Why (docs/tracking_evidence.md "Session 30"): ``family_min_links`` keeps
        the families from three-range nodes because a family chosen after the fact is tested
        by no other range; but a family's SNR is evidence no range gives, and the emulator's
        amplitude model of the slab series matches Sionna RT's (the 3-UAV building's
        ``Tx-R(ceiling)-R(floor)-R(ceiling)-Rx`` 19.4 dB predicted / 19.0 traced,
        ``Tx-D(lower)-R(ceiling)-R(floor)-Rx`` 7.4 / 7.7 dB). With three ranges the true
        floor fits the out-of-model first arrival with a wrong one of the 18 inside
        ``nis_limit`` (never a misfit, so the misfit gate never offers the exact family),
        hence every fitted link. Nodes with more ranges keep the other settings' gate and
        scoring; nodes with fewer than ``min_anchors_tracking`` ranges too (the ranges do
        not fix their position: a family on every link only adds freedom; measured on Sionna
        ``large``, whose one-to-two-range walker n02 went from 24 to 167 wrong node-epochs
        without this bound). Measured (replays, today's default + 3): Sionna heldout-2 91.37
        -> 95.18 % (every seed up), random buildings 99.70 -> 99.73, paper / main inert, but
        Sionna ``large`` s3 -0.63 (mean +0.11), the 95 % ellipsoid above 99 % on three
        heldout-2 seeds (the family-explained link leaves the fit) and x1.5 fusion CPU on
        the 3-UAV building: not a default alone. Default 3 (since 2026-12-08, with
        ``family_fit_links`` 3 and ``cov_few_floors`` "temper"; session 32 in
        docs/tracking_evidence.md: Sionna heldout-2 91.37 -> 97.37 %, every other set within
        0.05 points, x1.34 tracker CPU on the 3-UAV building, x1.01 on ``large``).
    family_fit_links : int [ranges]
        (``max_order`` > 2) At a node with at most this many ranges (and at least
        ``min_anchors_tracking``) a link the hypothesis' update left out of the fit (an
        outlier) whose out-of-model component an extra family explains (the families' part
        larger than the uniform outlier's; ``family_few_links`` offers them at three ranges)
        stays in the fit as that family's path: the hypothesis' prior is updated by the
        range with the most probable family's length and Jacobian at the clamped prior
        (linearised there, the range variance plus the families' spread), and the IEKF of
        the other links runs from it with the same mechanisms
        (:func:`diffpos.tracking.model.family_refit`). The link's log-weight already holds
        the families' predictive density at the prior, so the evidence becomes the joint
        ``p(family link) p(other links | family link)`` and the covariance keeps the
        range's information (with ``family_few_links`` alone the link leaves the fit: the
        covariance of two ranges with the error of three, the 95 % ellipsoid above 99 %).
        Default 3 (since 2026-12-08, with ``family_few_links`` 3 and ``cov_few_floors``
        "temper"); 0: off. The link still counts as an outlier for the learned arrays. Above
        three: a refitted level pair with four ranges or more that the edge retry
        (``edge_retry_margin_m``) updates again takes the retry's update (no family).
        Measured: docs/tracking_evidence.md "Session 31".
    challenger_m : float [m]
        A second position mode per floor (a *challenger* of the floor's level track; 0: off,
        the default, replays unchanged; :func:`diffpos.tracking.tracker._challengers`). Every
        ``challenger_period_s`` each floor (of the ``challenger_floors`` most probable after
        the leading one) of a TRACKING node with at least
        ``reseed_min_links`` (and four) ranges and no challenger is snapshot (the grid's best
        cell), and with ``challenger_loo_max_links`` also once per range left out; of the
        candidates whose horizontal distance from the floor's level track exceeds this value
        the one with the best evidence of one update with every range (from the level
        track's prior moved there) starts the floor's challenger: a level-mode Gaussian
        predicted and updated every epoch alongside the track (the prior link weights, no
        mechanism history), scored against the level track updated from its own prior with
        the same inputs. Its accumulated log-likelihood ratio (after ``challenger_grace``
        updates) above ``challenger_nats`` replaces the level track's state by the
        challenger's (the floor's probability kept: the evidence decides from then on);
        below ``-challenger_nats``, after ``challenger_epochs`` updates, within half this
        distance of the track, or with fewer ranges it is dropped. Why: a floor's only level
        track can settle in the wrong basin of a four-range fit (one out-of-model first
        arrival fitted by a wrong mechanism) while the truth would gain ~4 nats per epoch
        once a track is there; one epoch's snapshot cannot tell the basins apart
        (docs/channel_mix.md "Session 28: rand-2-0 at order 3"; docs/tracking_evidence.md
        "Session 29: a second position mode per floor"). Measured at 1.5 with
        ``challenger_beat_lead`` (replays): rand-2-0 at emulator order 3, nine runs, 91.41 ->
        94.78 % right floor (the 8 s system-test run 76.11 -> 94.17), Sionna paper s0u-s4
        90.20 -> 90.80 (s0u -1.2, s4 +4.2), the main command's twelve seeds identical; the
        tracker's CPU x2.2 (x1.3 with ``challenger_period_s`` 3, ``challenger_floors`` 1): not
        the default.
    challenger_period_s : float [s]
        With ``challenger_m``: each floor of a node is searched for a challenger once per
        this period (floor ``f`` at phase ``f / F``, measurement time since the node's
        origin, as the deficit test's schedule).
    challenger_nats : float [nats]
        With ``challenger_m``: the accumulated log-likelihood ratio that replaces the level
        track (or, negative, drops the challenger).
    challenger_grace : int
        With ``challenger_m``: a challenger's first updates not scored (its snapshot's broad
        prior costs it an Occam factor while it converges).
    challenger_epochs : int
        With ``challenger_m``: a challenger's scored updates before it is dropped undecided.
    challenger_min_p : float [-]
        With ``challenger_m``: only floors whose probability (after the epoch's update) is at
        least this value are searched (a floor far below its neighbours takes its state from
        them through the mixing every epoch, so a challenger of its own basin would keep
        winning against a track that keeps coming back); 0: any.
    challenger_beat_lead : bool
        With ``challenger_m``: the challenger is scored against the better of its floor's
        track and the node's most probable hypothesis (updated with the same inputs): it
        wins only where it would be the node's best explanation, so a search that finds
        wrong floors better positions (as often as the true floor's) does not strengthen
        a floor that stays behind.
    challenger_min_epochs : int
        With ``challenger_m``: the fewest scored updates before a challenger can win (a
        transient advantage, e.g. while the walker is on the stairs, does not replace the
        floor's track).
    challenger_loo_max_links : int
        With ``challenger_m``: nodes with 4 to this many ranges also get a candidate per range
        left out (the snapshot without that range: three ranges fit a position, an
        out-of-model fourth no longer pulls it); 0: the full snapshot only.
    challenger_floors : int
        With ``challenger_m``: only the node's this many most probable floors after its
        leading one (after the epoch's update) are searched for a challenger (bounded cost;
        the leading floor's track is not challenged: a better position there changes no
        floor decision, and on the stairs it moved the track the next floor mixes from);
        0: every floor.
    silent_anchor_nats : float [nats]
        Negative information of a silent anchor (:mod:`diffpos.tracking.silent`; 0: off,
        the default, replays unchanged): an anchor that reported for a node's epoch but
        detected no path (the wire's null range; the fusion passes its position with
        ``snr_db`` -inf and the link masked) costs each hypothesis ``-log(e + (1 - e)
        Phi((T + margin - S) / SNR_SIGMA_DB))`` nats, ``S`` the strongest slot's SNR the
        emulator's amplitude model predicts at the hypothesis' mean, ``T`` the detector's
        threshold (``Radio.detection_snr_db``) and ``e = exp(-silent_anchor_nats)``: at most
        this value per silent anchor and epoch (a model that predicts a path tens of dB too
        strong costs a bounded amount), nothing where the model predicts no path above the
        threshold plus the margin.
    silent_anchor_margin_db : float [dB]
        With ``silent_anchor_nats``: how far the predicted strongest path may exceed the
        detector's threshold before silence costs anything (the amplitude model's error on
        channels we did not write: Sionna's partitions and dielectric edges differ from the
        emulator by several dB).
    silent_anchor_max_links : int
        With ``silent_anchor_nats``: only nodes with at most this many ranges in the epoch
        (0: every node).
    silent_anchor_spread : bool
        With ``silent_anchor_nats``: the probability of the silence averaged over six
        sigma points of each hypothesis' position covariance
        (:func:`diffpos.tracking.silent.sigma_points`), not read at its mean alone: a
        hypothesis placed by two ranges is a spread of positions, some of them in the
        anchor's shadow. Default False.
    floor_hold_max_links : int
        Nodes with 1 to this many ranges in an epoch keep their floor probabilities (every
        hypothesis' log-probability as predicted; positions updated as before;
        :func:`diffpos.tracking.tracker._more_floor_evidence`): one or two ranges cannot
        place a node, every floor's hypothesis fits them, and what tells the floors apart is
        the amplitude model alone, which drifts on a channel we did not write (Sionna
        `large`'s top-floor walkers losing their ranges). Default 2 (since 2026-12-07 23:50
        UTC: Sionna `large` ten seeds 93.67 -> 94.25 %); 0: off.
    stairs_follow : int
        With ``mixing`` "select": before the prediction, hypotheses take the horizontal state
        (x, y, vx, vy and their covariance) of their node's most probable hypothesis and keep
        their own height and vertical speed (:func:`diffpos.tracking.imm._follow_leader`):
        bit 1 (1 or 3), the other mode of the leader's floor (the vertical mode of a level
        walker, the level mode of one on the stairs); bit 2 (2 or 3), the vertical modes of
        the floors next to the leader's (the stairs to the floor above and below start where
        the walker is).
        The other floors' level modes keep their own tracks. Default 3 (since 2026-12-08,
        with ``stairs_follow_settled_s`` 1, ``stairs_follow_m`` 1, ``stairs_follow_min_links``
        4: Sionna paper twenty seeds 90.61 -> 94.40 %, `large` -0.17, the emulator's main
        command -0.01; docs/tracking_evidence.md "Session 32, lead"); 0: off. Why: the
        walker's horizontal position does not depend on its mode; on Sionna RT's paper
        building the climbing walker's vertical mode was 3-7 m off while its level mode was
        at 0.1 m, so at a floor change no hypothesis of the true floor was near the walker
        (docs/tracking_evidence.md "Session 32").
    stairs_follow_settled_s : float [s]
        With ``stairs_follow``: only nodes whose most probable floor has not been contested
        (``TrackerState.lead_ns``, the rule of ``floor_contest_s``) for at least this long;
        0: every node. Why: a leader that has just taken over may be a mirror floor, whose
        horizontal position is wrong for every other floor (measured: the true floor's
        vertical mode dragged 3.6 m off by a mirror floor that led for one second).
        Default 1.
    stairs_follow_after_s : float [s]
        With ``stairs_follow``: only nodes tracked for at least this long since their
        snapshot initialisation (``TrackerState.refresh_origin_ns``: the first one or a
        re-initialisation after a loss), before their last update. Why: at
        start-up a wrong floor may lead the first second, long enough to count as settled
        (``stairs_follow_settled_s``), and the followers follow it (measured: a fresh Sionna
        paper seed, 16, lost 12.3 points at start-up; docs/tracking_evidence.md "Session 32"; on
        twenty paper seeds at 3 s a wash: seed 16 back, seeds 0, 3, 8-10 -2..-6). 0: off (default).
    stairs_follow_m : float [m]
        With ``stairs_follow``: only followers whose horizontal mean is farther than this
        from the leader's are re-placed (those that drifted away); a follower nearer keeps
        its own track. 0: every follower, every epoch. Why: a level mode's horizontal
        estimate is biased while the walker climbs (its height prior pins the height, the
        ranges' misfit goes into x, y), and given every epoch with the level mode's small
        covariance it pulled the vertical mode's height to the wrong end of the band
        (measured on the emulator's main command, seed 3). Default 1.
    stairs_follow_min_links : int
        With ``stairs_follow``: only nodes with at least this many ranges in the epoch
        predicted to (a prediction without ranges: none); 0: every node. Why: three ranges
        fit every floor, so a leader placed by three ranges says little about where the
        walker is (measured on Sionna RT's 3-UAV building: every variant lost 1.4-5.9
        points there; the rule of ``reseed_min_links``). Default 4.
    """

    q_h_m2_s3: float = 1.5
    q_v_m2_s3: float = 0.36
    v_level_sigma_m_s: float = 0.1
    v_stairs_m_s: float = 0.6
    jump_rate_hz: float = 1e-3
    z_mix_sigma_m: float = 0.5
    z_margin_m: float = 0.05
    box_sigma_m: float = 0.02
    exist_margin_m: float = 0.2
    height_sigma_m: float = 0.3
    stairs_weight: float = 0.1
    sigma_model_m: float = 0.03
    outlier_weight: float = 0.02
    outlier_span_m: float = 30.0
    mixing: str = "select"
    gn_iterations: int = 3
    select_passes: int = 2
    init_grid_m: float = 2.0
    init_starts: int = 3
    init_sigma_v_m_s: float = 1.0
    start_grid_m: float = 0.0
    min_ranges_init: int = 3
    confirm_epochs: int = 5
    lost_after_s: float = 5.0
    nis_limit: float = 9.0
    nis_alpha: float = 0.2
    diverge_epochs: int = 10
    reseed_epochs: int = 3
    reseed_max: int = 2
    dormant: bool = True
    dormant_margin_nats: float = 3.0
    dormant_refresh_s: float = 1.0
    dormant_epochs: int = 1
    dormant_floor_p: float = 0.0
    floor_evidence_lag1_corr: float = 0.59
    snr_reuse_m: float = 0.05
    snr_reuse_anchor_m: float = 0.1
    snr_cost_cap_nats: float = 4.5
    link_learn: bool = True
    link_forget: float = 0.95
    link_prior_updates: float = 10.0
    link_outlier_max: float = 0.5
    link_bias_learn: bool = False
    link_bias_q_m2_s: float = 0.1
    link_snr_gain: float = 0.3
    link_match_m: float = 1.0
    link_learn_minority: bool = False
    link_learn_unexplained: bool = False
    lost_on_gap: bool = True
    min_anchors_tracking: int = 3
    few_anchors_floor_p_max: float = 0.75
    max_order: int = 3
    family_weight: str = "mechanism"
    family_gate: str = "misfit"
    family_history: int = 1
    family_min_links: int = 5
    family_minority: bool = True
    family_first: bool = False
    family_learned_links: int = 4
    family_snr: bool = False
    family_select: bool = False
    family_select_min_links: int = 0
    family_worst_min_links: int = 4
    family_worst_nis: float = 1.0
    family_worst_outliers: bool = False
    family_worst_outliers_settled: bool = False
    family_fit: str = "prior"
    floor_model_doubt: bool = True
    floor_robust_links: int = 0
    floor_contest_s: float = 3.0
    floor_contest_kappa: float = 10.0
    floor_contest_vertical: bool = False
    floor_band_bound: bool = False
    cov_published_floors: str = "credible"
    cov_few_floors: str = "temper"
    mode_search_outliers: int = 0
    mode_jump_rate_hz: float = 0.0
    mode_jump_sigma_m: float = 2.0
    mode_search_max: int = 0
    mode_search_min_links: int = 0
    reseed_min_links: int = 4
    reseed_period_s: float = 0.0
    reseed_starts: int = 0
    mode_search_new_misfit: float = 0.0
    deficit_nats: float = 0.0
    deficit_tests: int = 2
    deficit_period_s: float = 1.0
    deficit_level_only: bool = False
    deficit_exact: bool = False
    deficit_quiet_every: int = 2
    first_arrival_prior: float = 0.8
    edge_retry_margin_m: float = 0.4
    edge_retry_eps: float = 0.05
    mechanism_prior_min_links: int = 4
    edge_retry_prior: bool = False
    edge_retry_node: bool = True
    mechanism_switch_p: float = 0.3
    link_eps_node: bool = False
    link_eps_node_awake: bool = False
    reseed_outliers: int = 2
    snr_diffraction_slack_db: float = 6.0
    snr_slack_max_links: int = 3
    snr_slack_skip: bool = False
    snr_edge_model: str = "halfplane"
    link_eps_posterior: int = 0
    skip_threshold_order: int = 0
    skip_threshold_max_links: int = 3
    family_few_links: int = 3
    family_fit_links: int = 3
    link_eps_lend_contest_s: float = 0.0
    link_eps_lend_below_p: float = 0.0
    link_eps_lend_fewer: bool = False
    challenger_m: float = 0.0
    challenger_period_s: float = 1.0
    challenger_nats: float = 6.0
    challenger_grace: int = 3
    challenger_epochs: int = 30
    challenger_loo_max_links: int = 5
    challenger_floors: int = 2
    challenger_min_epochs: int = 1
    challenger_min_p: float = 0.0
    challenger_beat_lead: bool = False
    silent_anchor_nats: float = 0.0
    silent_anchor_margin_db: float = 10.0
    silent_anchor_max_links: int = 0
    silent_anchor_spread: bool = False
    floor_hold_max_links: int = 2
    stairs_follow: int = 3
    stairs_follow_settled_s: float = 1.0
    stairs_follow_after_s: float = 0.0
    stairs_follow_m: float = 1.0
    stairs_follow_min_links: int = 4


@dataclass(frozen=True)
class TrackerState:
    """Filter bank of every node (arrays over N nodes and H = 2F hypotheses: hypothesis
    ``h = mode * F + floor``, mode 0 level, 1 vertical; :func:`hypothesis_floor`,
    :func:`hypothesis_vertical`).

    Attributes
    ----------
    mean : ndarray, shape (N, H, 6) [m, m/s]
    cov : ndarray, shape (N, H, 6, 6)
    log_prob : ndarray, shape (N, H)
        Normalised joint log-probability of every (floor, mode) hypothesis.
    status : ndarray of int8, shape (N,)
        :class:`TrackStatus`.
    t_ns : ndarray of int64, shape (N,) [ns]
        Time the state refers to.
    last_fix_ns : ndarray of int64, shape (N,) [ns]
        Last epoch with usable ranges.
    nis : ndarray, shape (N,)
        Averaged NIS per used range.
    good, bad : ndarray of int, shape (N,)
        Consecutive consistent / inconsistent epochs.
    floor_bad : ndarray of int, shape (N, H)
        Consecutive epochs in which a hypothesis explained fewer than half of the ranges
        or had an NIS above ``nis_limit`` (at ``reseed_epochs`` it is re-seeded from a
        snapshot of that floor).
    dormant_llr : ndarray, shape (N, H)
        NaN for a hypothesis that is updated every epoch; for a *dormant* one its log
        likelihood ratio to the node's best hypothesis at its last real update (<= 0), which
        stands in for its evidence until the next real update.
    updated_ns : ndarray of int64, shape (N, H) [ns]
        Time of each hypothesis' last real measurement update (the refresh schedule of the
        dormant ones).
    below_epochs : ndarray of int, shape (N, H)
        Consecutive real updates with the hypothesis below the dormant threshold (dormant
        from ``dormant_epochs`` on).
    refresh_origin_ns : ndarray of int64, shape (N,) [ns]
        Origin of the node's refresh schedule (its snapshot initialisation): the schedule
        depends on time differences only, so shifting every input time by a constant
        changes no output.
    snr_node : ndarray, shape (N, H, 3) [m]
        Where every hypothesis' SNR predictions ``snr_pred`` were made (NaN: none).
    snr_anchor : ndarray of float32, shape (N, H, SNR_CACHE_LINKS, 3) [m]
        The anchor of every cached link (column of the update's links; NaN: none).
    snr_pred : ndarray of float32, shape (N, H, SNR_CACHE_LINKS, len(SNR_CACHE_SLOTS)) [dB]
        Predicted SNR of the slots ``SNR_CACHE_SLOTS`` of the cached links at ``snr_node``
        (-inf: no power). float32: the state is copied every update (row selection, write
        back), so its size is CPU; a reused SNR is rounded by < 1e-5 dB.
    link_anchor : ndarray, shape (N, L, 3) [m]
        The anchor position of every learned link (:mod:`diffpos.tracking.evidence`; NaN:
        free), ``link_seen_ns`` (N, L) when it was last present.
    link_out, link_all : ndarray, shape (N, H, L)
        Forgotten counts of a hypothesis' real updates in which the link was an outlier /
        present.
    link_ev : ndarray, shape (N, H, L) [nats]
        Forgotten sum (``link_forget``) of the link's share of the hypothesis' log-evidence
        per real update (its mixture log-weight and range term; the published floor
        probabilities' one-link-out robustness, ``TrackerConfig.floor_robust_links``).
    link_bias, link_bias_var : ndarray, shape (N, H, L) [m], [m^2]
        Learned excess delay of the link over the straight line while an outlier (NaN: none).
    link_snr : ndarray, shape (N, H, L) [dB]
        Learned mean SNR of the link while an outlier (NaN: none).
    link_t_ns : ndarray of int64, shape (N, H, L) [ns]
        When the excess delay was last updated.
    lead_floor : ndarray of int, shape (N,)
        The most probable floor (of the filter) after the node's last update (-1: none).
    lead_ns : ndarray of int64, shape (N,) [ns]
        The last update in which the node's floor was contested (:func:`floor_contested`;
        ``TrackerConfig.floor_contest_s``).
    unexplained, redundant : ndarray, shape (N,)
        Forgotten counts (``link_forget`` per counted epoch) of the node's epochs with a
        redundant range (at least four) in which every hypothesis misfit a present link at its
        last real update / of all such epochs (:func:`diffpos.tracking.evidence.unexplained_log_odds`;
        ``TrackerConfig.family_learned_links``).
    link_slot : ndarray, shape (N, H, L)
        The mechanism slot every hypothesis chose for every learned link at its last update
        with the link present (-1: an outlier; NaN: none; ``TrackerConfig.mechanism_switch_p``;
        only kept with the setting on).
    deficit_count : ndarray of int, shape (N, H)
        Consecutive evidence-deficit tests of every hypothesis whose floor's snapshot was
        better by more than ``TrackerConfig.deficit_nats`` (at ``deficit_tests`` it is
        re-seeded; 0 with the setting off).
    chal_mean, chal_cov : ndarray, shape (N, F, 6), (N, F, 6, 6)
        Every floor's challenger of its level track (``TrackerConfig.challenger_m``; its
        Gaussian after the node's last update).
    chal_llr : ndarray, shape (N, F) [nats]
        The challenger's accumulated log-likelihood ratio to the level track.
    chal_age : ndarray of int, shape (N, F)
        The challenger's updates since it started (0: no challenger).
    """

    mean: FloatArray
    cov: FloatArray
    log_prob: FloatArray
    status: NDArray[np.int8]
    t_ns: NDArray[np.int64]
    last_fix_ns: NDArray[np.int64]
    nis: FloatArray
    good: NDArray[np.int_]
    bad: NDArray[np.int_]
    floor_bad: NDArray[np.int_]
    dormant_llr: FloatArray
    updated_ns: NDArray[np.int64]
    below_epochs: NDArray[np.int_]
    refresh_origin_ns: NDArray[np.int64]
    snr_node: FloatArray
    snr_anchor: FloatArray
    snr_pred: FloatArray
    link_anchor: FloatArray
    link_seen_ns: NDArray[np.int64]
    link_out: FloatArray
    link_all: FloatArray
    link_ev: FloatArray
    link_bias: FloatArray
    link_bias_var: FloatArray
    link_snr: FloatArray
    link_t_ns: NDArray[np.int64]
    link_fit: FloatArray
    unexplained: FloatArray
    redundant: FloatArray
    lead_floor: NDArray[np.int_]
    lead_ns: NDArray[np.int64]
    deficit_count: NDArray[np.int_]
    link_slot: FloatArray
    chal_mean: FloatArray
    chal_cov: FloatArray
    chal_llr: FloatArray
    chal_age: NDArray[np.int_]


@dataclass(frozen=True)
class TrackOutput:
    """Published estimate of every node.

    Attributes
    ----------
    position_m : ndarray, shape (N, 3) [m]
        NaN where no position is published (UNINITIALISED, LOST).
    covariance_m2 : ndarray, shape (N, 3, 3) [m^2]
    floor_index : ndarray of int, shape (N,)
        Most probable floor (-1 without a position).
    floor_probabilities : ndarray, shape (N, F)
    status : ndarray of int8, shape (N,)
    mechanism : ndarray of int, shape (N, M)
        Slot of :data:`diffpos.paths.mechanisms.MECHANISMS` used per anchor on the chosen floor (-1:
        missing or treated as an outlier).
    residual_m : ndarray, shape (N, M) [m]
        Range minus the chosen mechanism's length at the estimate (NaN where -1).
    nis : ndarray, shape (N,)
        Averaged normalised innovation per used range.
    """

    position_m: FloatArray
    covariance_m2: FloatArray
    floor_index: NDArray[np.int_]
    floor_probabilities: FloatArray
    status: NDArray[np.int8]
    mechanism: NDArray[np.int_]
    residual_m: FloatArray
    nis: FloatArray


def n_floors_of(state: TrackerState) -> int:
    """Number of floors of a state (its hypotheses are floors x 2 vertical modes)."""
    return state.log_prob.shape[1] // 2


def few_ranges(n_meas: ArrayLike, max_links: int, min_links: int = 0) -> NDArray[np.bool_]:
    """The nodes a few-range setting applies to: ``n_meas`` ranges (N,) at most ``max_links``
    (0: any number) and at least ``min_links`` (the settings' ``*_max_links`` /
    ``family_few_links`` with ``min_anchors_tracking``)."""
    n = np.asarray(n_meas)
    few = n >= min_links
    return few & (n <= max_links) if max_links > 0 else few


def clamp_to_floor(x: FloatArray, floor, building, margin_m: float) -> FloatArray:
    """Keep every hypothesis' position inside its floor's box (``margin_m`` from the walls)."""
    zf = building.floor_z_m(np.asarray(floor))
    x0, x1 = building.edge_x_m
    out = x.copy()
    out[..., 0] = np.clip(x[..., 0], x0 + margin_m, x1 - margin_m)
    out[..., 1] = np.clip(x[..., 1], margin_m, building.depth_m - margin_m)
    out[..., 2] = np.clip(x[..., 2], zf + margin_m, zf + building.floor_height_m - margin_m)
    return out


@functools.lru_cache(maxsize=64)
def hypothesis_floor(n_floors: int) -> NDArray[np.int_]:
    """Floor of every hypothesis ``h = mode * F + floor``, shape (2F,) (one read-only array
    per ``n_floors``: built once, not on every tracker call)."""
    out = np.tile(np.arange(n_floors), 2)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=64)
def hypothesis_vertical(n_floors: int) -> NDArray[np.bool_]:
    """Vertical mode (stairs) of every hypothesis, shape (2F,) (the first F are level; one
    read-only array per ``n_floors``)."""
    out = np.repeat([False, True], n_floors)
    out.flags.writeable = False
    return out


def floor_probabilities(log_prob: ArrayLike, prob: FloatArray | None = None) -> FloatArray:
    """Floor marginals (N, F) of the hypotheses' log-probabilities (N, H = 2F) (e.g.
    :attr:`TrackerState.log_prob`): the sum of every floor's two vertical modes
    (``prob``: ``exp(log_prob)`` if the caller has it)."""
    p = np.exp(np.asarray(log_prob, dtype=np.float64)) if prob is None else prob
    nf = p.shape[-1] // 2
    return p[..., :nf] + p[..., nf:]


def floor_reweighted(prob_h: FloatArray, q: FloatArray) -> FloatArray:
    """Hypothesis weights (N, H = 2F) whose floor marginals are ``q`` (N, F) (e.g. the
    published floor probabilities), each floor's two modes split as in ``prob_h`` (N, H)
    (evenly where ``prob_h`` gives the floor no mass); rows of ``q`` with a NaN give NaN."""
    nf = q.shape[-1]
    p = floor_probabilities(None, prob_h)
    tiny = p <= 1e-300
    share = np.where(tiny, 0.5, prob_h[..., :nf] / np.where(tiny, 1.0, p))
    return np.concatenate([q * share, q * (1.0 - share)], axis=-1)


def credible_floor_weights(q: FloatArray, p: FloatArray, mass: float = 0.95) -> FloatArray:
    """Per floor (N, F) the published probability ``q`` for the floors of the smallest set of
    most probable floors (by ``q``) whose mass reaches ``mass``, the filter's ``p`` for the
    others."""
    order = np.argsort(-q, axis=-1, kind="stable")
    qs = np.take_along_axis(q, order, axis=-1)
    before = np.cumsum(qs, axis=-1) - qs  # the mass of the more probable floors
    inside = np.zeros(q.shape, bool)
    np.put_along_axis(inside, order, before < mass, axis=-1)
    return np.where(inside, q, p)


def mixture_mse_cov(mean: FloatArray, cov: FloatArray, w_h: FloatArray, pos: FloatArray,
                    best: NDArray[np.int_], p_best: FloatArray, vf: FloatArray) -> FloatArray:
    """The published covariance (N, 3, 3) [m^2] of the point ``pos`` (N, 3): the best floor's
    mode-mixture covariance ``vf * sum_m w_m P_m`` (``vf`` (N,) the variance factor, ``w_m``
    the best floor's two modes' shares), the spread ``sum_h w_h d_h d_h^T`` of every
    hypothesis' mean about the point (weights ``w_h`` (N, H)) and the best floor's mode
    spread for the mass ``1 - p_best`` not on it. ``mean`` (N, H, >=3), ``cov`` (N, H, >=3,
    >=3), ``best`` (N,) the best floor, ``p_best`` (N,) its probability under ``w_h``."""
    n, h = w_h.shape
    nf, rows = h // 2, np.arange(n)
    pair = np.stack([best, best + nf], axis=1)
    w = w_h[rows[:, None], pair]
    w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    pm = np.einsum("nm,nmij->nij", w, cov[rows[:, None], pair, :3, :3])
    d = mean[..., :3] - pos[:, None]
    dm = mean[rows[:, None], pair, :3] - pos[:, None]
    return (vf[:, None, None] * pm + np.einsum("nh,nhi,nhj->nij", w_h, d, d)
            + np.einsum("nm,nmi,nmj->nij", w * (1.0 - p_best)[:, None], dm, dm))


def evidence_temper(config: TrackerConfig) -> float:
    """``kappa = (1 + rho) / (1 - rho)``, ``rho = config.floor_evidence_lag1_corr``: how many
    epochs of correlated evidence carry the information of one independent epoch (the
    variance inflation of a sum of AR(1) terms, i.e. ``n_eff = n / kappa``)."""
    rho = float(np.clip(config.floor_evidence_lag1_corr, 0.0, 0.99))
    return (1.0 + rho) / (1.0 - rho)


def published_floor_probabilities(log_prob: ArrayLike, config: TrackerConfig,
                                  prob: FloatArray | None = None, *,
                                  link_ev: FloatArray | None = None,
                                  link_all: FloatArray | None = None,
                                  doubt: FloatArray | None = None,
                                  contested: NDArray[np.bool_] | None = None) -> FloatArray:
    """The floor probabilities the tracker publishes (:attr:`TrackOutput.floor_probabilities`),
    (N, F): the floor marginals of :func:`floor_probabilities` raised to ``1 / kappa``
    (:func:`evidence_temper`) and renormalised, i.e. every log-odds between two floors divided
    by ``kappa``. Monotone: the most probable floor is unchanged.

    Why: every epoch adds each hypothesis' marginal likelihood to its log-probability as if
    the epochs were independent, but the model errors behind it (unmodelled multipath, a
    mechanism mis-selection, the height ambiguity) persist while the node moves ~12 cm per
    epoch. Measured on the lockstep emulation (``benchmarks/bench_tracking.py
    --evidence-corr``: the per-epoch change of the floor marginals, true floor minus the best
    wrong floor, dormant hypotheses off; default, other-building and anchors-beyond-ends,
    seeds 0-1, 20 s, 36 tracked nodes): lag-1 autocorrelation 0.59 (median over nodes; mean
    0.55), 0.35 at 0.5 s, 0.16 at 1 s, ~0 at 3 s; on three variant geometries of our own (6
    floors of 3.4 m with low UAVs and with UAVs at 5-16 m, 4 floors of 3.2 m with UAVs beyond
    the facade ends) 0.56. For an AR(1) sequence of evidence increments with correlation
    ``rho`` the sum over ``n`` epochs has the variance of ``n / kappa`` independent ones, so
    its log-likelihood ratio is worth ``1 / kappa`` of its face value (the magnitude
    adjustment of a composite likelihood). ``rho = 0.59`` gives ``kappa = 3.9``. The full
    measured curve (its tail beyond 0.1 s is heavier than AR(1)) would give ``1 + 2 sum
    rho_k = 10``, which was underconfident (over the ``--reliability`` ensemble: published
    0.83, right 99.7 %): with the floor jump the filter's log-odds keep a memory of only a
    few epochs (``ln(1 / jump)`` plus the latest epochs' evidence), so the long tail is not
    summed. Published only: the filter's hypotheses, the chosen floor and the position are
    exactly those of the untempered tracker. Reliability before and after
    (``bench_tracking.py --reliability``, 18,000 node-epochs): estimates published at
    >= 0.99 right 95.6 -> 99.8 %, log loss 0.60 -> 0.24 nats; below 0.9 still
    overconfident (long wrong-floor locks).

    ``contested`` (N,) bool: the nodes whose floor was contested less than
    ``config.floor_contest_s`` ago (the tracker's; None or the setting 0: none); their
    log-odds are divided by ``config.floor_contest_kappa`` instead (the lead built since the
    contest is a sum of correlated evidence, ``TrackerConfig.floor_contest_s``).
    """
    p = floor_probabilities(log_prob, prob)
    kappa = evidence_temper(config)
    if contested is not None and config.floor_contest_s > 0 and np.any(contested):
        kappa = np.where(np.asarray(contested, bool), max(float(config.floor_contest_kappa), 1.0),
                         kappa)[:, None]
    robust = link_ev is not None and config.floor_robust_links > 0 and config.link_learn
    if np.ndim(kappa) == 0 and kappa == 1.0 and not robust:
        return _mix_uniform(p, doubt)
    if robust:
        e0 = float(config.outlier_weight)
        lf = robust_floor_log_prob(np.asarray(log_prob, dtype=np.float64), link_ev, link_all,
                                   config.floor_robust_links, float(np.log((1 - e0) / e0)))
        lp = np.maximum(lf, np.log(1e-300)) / kappa
    else:
        lp = np.log(np.maximum(p, 1e-300)) / kappa
    lp = lp - lp.max(axis=-1, keepdims=True)
    q = np.exp(lp)
    return _mix_uniform(q / q.sum(axis=-1, keepdims=True), doubt)


def floor_contested(log_prob: FloatArray, lead_floor: NDArray[np.int_], n_meas: NDArray,
                    prob: FloatArray | None = None, *, vertical: bool = False
                    ) -> tuple[NDArray[np.bool_], NDArray[np.int_]]:
    """Whether every node's floor is *contested* in this update, and its most probable floor
    (N,) (``TrackerConfig.floor_contest_s``): the most probable floor of the filter differs from
    ``lead_floor`` (the previous update's), or its probability is below 1/2 (no floor has
    the majority), or the node has fewer than four ranges ``n_meas`` (three ranges fit a
    position on any floor, so the ranges did not test the floor). ``prob``: ``exp(log_prob)``
    if the caller has it. ``vertical`` (``TrackerConfig.floor_contest_vertical``): also
    contested when the most probable floor's vertical (stairs) mode is more probable than its
    level mode."""
    prob = np.exp(log_prob) if prob is None else prob
    pf = floor_probabilities(log_prob, prob)
    top = np.argmax(pf, axis=1)
    rows = np.arange(pf.shape[0])
    p_top = pf[rows, top]
    contested = (top != lead_floor) | (p_top < 0.5) | (np.asarray(n_meas) < 4)
    if vertical:
        contested |= prob[rows, top + pf.shape[1]] > prob[rows, top]
    return contested, top


def height_band_bound(p: FloatArray, floor: NDArray[np.int_], z_m: FloatArray,
                      var_z_m2: FloatArray, first_floor_z_m: float,
                      floor_height_m: float) -> FloatArray:
    """Floor probabilities ``p`` (N, F) with the published floor's capped at its height band's
    mass (``TrackerConfig.floor_band_bound``): ``floor`` (N,) the published floor (-1: none,
    the row unchanged), ``z_m`` (N,) [m] and ``var_z_m2`` (N,) [m^2] the published height and
    its variance (non-finite: unchanged).

    Band of floor ``f``: ``[z0 + f H, z0 + (f + 1) H)`` (``z0 = first_floor_z_m``, ``H =
    floor_height_m``; the lowest band extended to -inf, the highest to +inf). Its mass under
    ``N(z, var)``, ``b_f``, bounds the probability of ``f`` that a position with that height
    distribution can support. The published floor ``k`` gets ``min(p_k, max(b_k, 1/2))``
    (1/2: it stays the most probable floor); what it loses goes to the other floors in
    proportion to their ``b_g`` (uniformly if every ``b_g`` is 0). Rows whose ``p_k`` is
    within the bound are returned bit for bit."""
    p = np.asarray(p, dtype=np.float64)
    n, nf = p.shape
    floor = np.asarray(floor)
    z, var = np.asarray(z_m, dtype=np.float64), np.asarray(var_z_m2, dtype=np.float64)
    k = np.where((floor >= 0) & (floor < nf), floor, 0)
    rows = np.flatnonzero((floor >= 0) & (floor < nf) & np.isfinite(z) & np.isfinite(var)
                          & (p[np.arange(n), k] > 0.5))  # the cap is >= 1/2
    if nf < 2 or rows.size == 0:
        return p
    k, z, sd = k[rows], z[rows], np.sqrt(np.maximum(var[rows], 1e-24))
    lo = np.where(k == 0, -np.inf, first_floor_z_m + k * floor_height_m)
    hi = np.where(k == nf - 1, np.inf, first_floor_z_m + (k + 1) * floor_height_m)
    near = np.minimum(hi - z, z - lo) < 9.0 * sd  # beyond 9 sigma the band's mass is 1.0
    rows, k, z, sd, lo, hi = rows[near], k[near], z[near], sd[near], lo[near], hi[near]
    if rows.size == 0:
        return p
    own = normal_cdf((hi - z) / sd) - normal_cdf((lo - z) / sd)
    excess = np.maximum(p[rows, k] - np.maximum(own, 0.5), 0.0)
    hit = excess > 0
    if not np.any(hit):
        return p
    rows, k, z, sd, excess = rows[hit], k[hit], z[hit], sd[hit], excess[hit]
    edges = first_floor_z_m + floor_height_m * np.arange(1, nf)  # (F - 1,) the inner slabs
    cdf = normal_cdf((edges[None, :] - z[:, None]) / sd[:, None])
    m = rows.size
    band = np.diff(np.concatenate([np.zeros((m, 1)), cdf, np.ones((m, 1))], axis=1), axis=1)
    others = np.arange(nf)[None, :] != k[:, None]
    w = np.where(others, band, 0.0)
    tot = w.sum(axis=1, keepdims=True)
    w = np.where(tot > 0, w / np.where(tot > 0, tot, 1.0), others / (nf - 1))
    out = p.copy()
    out[rows] = p[rows] + excess[:, None] * w
    out[rows, k] = p[rows, k] - excess
    return out


def _mix_uniform(p: FloatArray, doubt: FloatArray | None) -> FloatArray:
    """``(1 - doubt) p + doubt / F`` (the floor probabilities when the model may not hold)."""
    if doubt is None:
        return p
    w = np.clip(np.asarray(doubt, dtype=np.float64), 0.0, 1.0)[..., None]
    return (1.0 - w) * p + w / p.shape[-1]


def robust_floor_log_prob(log_prob: FloatArray, link_ev: FloatArray, link_all: FloatArray,
                          n_drop: int, cap_nats: float = 0.0) -> FloatArray:
    """Floor log-marginals (N, F) of the hypotheses' ``log_prob`` (N, H = 2F) with the
    evidence of the ``n_drop`` links that decide each floor's deficit most worth at most
    ``cap_nats``: the published floor probabilities' *one-link-out* robustness
    (``TrackerConfig.floor_robust_links``; :func:`published_floor_probabilities` passes
    ``cap_nats = ln((1 - e0) / e0)``, ``e0 = outlier_weight``).

    The most probable floor ``f*`` keeps its log-marginal. For every other floor ``g`` the
    best hypotheses of ``f*`` and ``g`` (over the vertical modes) are compared link by link
    on their forgotten per-link evidence ``link_ev`` (N, H, L) [nats] (links both have seen:
    ``link_all`` > 0): ``d_l = ev(f*, l) - ev(g, l)``, ``D = sum_l d_l``. The ``n_drop``
    largest positive ``d_l`` are a share ``s = min(sum of them / D, 1)`` of ``g``'s deficit
    ``G`` (0 where ``D <= 0``: the links do not favour ``f*``); ``g``'s deficit becomes
    ``G (1 - s) + min(G s, cap_nats)``. Why: a link whose first arrival is out of the path
    model is explained on a mirror floor by one of its own mechanisms while the true floor must
    call it an outlier, and it does so every epoch: one link then carries the whole floor
    decision (Sionna RT, paper building: 88 of 135 receivers with one out-of-model link on a
    wrong floor). Its repetition from epoch to epoch is not independent evidence (the same
    geometry, the same unmodelled arrival), so one link's persistent vote is worth at most the
    odds the model gives it of being one of its mechanisms, ``(1 - e0) / e0``; ``cap_nats``
    0 leaves that link out altogether. The filter itself is unchanged.
    """
    nf = log_prob.shape[1] // 2
    rows = np.arange(log_prob.shape[0])
    p = np.exp(log_prob)
    pf = p[:, :nf] + p[:, nf:]
    with np.errstate(divide="ignore"):
        lf = np.log(pf)
    if n_drop <= 0:
        return lf
    top = np.argmax(pf, axis=1)
    hbest = np.where(p[:, :nf] >= p[:, nf:], np.arange(nf), np.arange(nf) + nf)  # (N, F)
    hs = hbest[rows, top]
    seen = (link_all[rows, hs][:, None, :] > 0) & (link_all[rows[:, None], hbest] > 0)
    d = np.where(seen, link_ev[rows, hs][:, None, :] - link_ev[rows[:, None], hbest], 0.0)
    tot = d.sum(axis=-1)
    lead = -np.sort(-np.maximum(d, 0.0), axis=-1)[..., :n_drop].sum(axis=-1)
    s = np.where(tot > 0, np.minimum(lead / np.where(tot > 0, tot, 1.0), 1.0), 0.0)
    lf_top = lf[rows, top][:, None]
    with np.errstate(invalid="ignore"):
        gap = lf_top - lf
        out = np.where(np.isfinite(lf), lf_top - gap * (1.0 - s) - np.minimum(gap * s, cap_nats),
                       lf)
    return out
