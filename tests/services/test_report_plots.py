"""The report plots say what they show: every legend entry of the power-ratio figure is an
artist drawn on its axes (reference: the sweep's own line-of-sight mask), and the replay CDF
divides by every node-epoch (reference: the counts given)."""

from __future__ import annotations

import dataclasses

import numpy as np
from diffpos_services.reports import power_ratio
from diffpos_services.reports.replay import _denominator

from diffpos.channel.power_ratio import PowerRatioSweep, compute_sweep


def _legend_vs_artists(fig):
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    drawn = [a.get_label() for a in (*ax.lines, *ax.collections)]
    return labels, drawn


def test_every_power_ratio_legend_entry_is_drawn():
    cfg = PowerRatioSweep()
    sweep = compute_sweep(cfg)
    labels, drawn = _legend_vs_artists(power_ratio.figure(sweep, cfg, 10.0))
    assert labels and all(lab in drawn for lab in labels)
    band = [c for c in power_ratio.figure(sweep, cfg, 10.0).axes[0].collections
            if "line of sight" in c.get_label()]
    assert bool(band) == bool(np.asarray(sweep.los).any())
    # without any direct path the band is neither drawn nor listed
    no_los = dataclasses.replace(sweep, los=np.zeros_like(sweep.los))
    labels, _ = _legend_vs_artists(power_ratio.figure(no_los, cfg, 10.0))
    assert not any("line of sight" in lab for lab in labels)


def test_cdf_denominator_is_every_node_epoch():
    assert _denominator({"node_epochs": 1080}, 59) == (1080, "node-epochs")
    # without a node-epoch count (no truth grid) the fixes are the denominator, said so
    assert _denominator({}, 59) == (59, "fixes")
    assert _denominator(None, 59) == (59, "fixes")
