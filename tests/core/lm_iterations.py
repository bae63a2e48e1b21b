"""Test helper: count the Levenberg-Marquardt iterations D-NLS's numpy reference runs
(``diffpos.estimators.dnls.fit.levenberg_marquardt`` wrapped through ``monkeypatch``)."""

from __future__ import annotations

import diffpos.estimators.dnls.fit as dnls_fit


def count_lm_iterations(monkeypatch) -> dict:
    """A dict whose ``"it"`` grows by every LM call's iterations from now on (reset it to 0
    between the runs compared)."""
    count = {"it": 0}
    lm = dnls_fit.levenberg_marquardt

    def counting(*args, **kw):
        res = lm(*args, **kw)
        count["it"] += int(res.iterations.sum())
        return res

    monkeypatch.setattr(dnls_fit, "levenberg_marquardt", counting)
    return count
