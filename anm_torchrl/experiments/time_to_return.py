"""Time to a return threshold over seeds, with runs that never reach it counted as censored, not dropped.

A run that reaches the threshold gives an *event* at its time; a run that does not gives a *censored* time: its
whole run length (we only know the time to threshold exceeds it). Over seeds we report the Kaplan–Meier median
(``None`` when fewer than half the runs reached the threshold: the median is then beyond the longest run) and the
restricted mean (mean of event or censoring times; a lower bound of the mean when any run is censored).
"""

from __future__ import annotations

from typing import Any


def km_median(times: list[float], reached: list[bool]) -> float | None:
    """Kaplan–Meier median of event times ``times`` (s) with ``reached[i] = False`` marking a censored time."""
    if len(times) != len(reached):
        raise ValueError(f"times and reached must have the same length, got {len(times)} and {len(reached)}")
    order = sorted(range(len(times)), key=lambda i: (times[i], not reached[i]))  # events before censoring at a tie
    at_risk, survival = len(times), 1.0
    for i in order:
        if reached[i]:
            survival *= 1.0 - 1.0 / at_risk
            if survival <= 0.5:
                return float(times[i])
        at_risk -= 1
    return None


def censored_summary(runs: list[dict[str, Any]], key: str, offset_s: float = 0.0) -> dict[str, Any]:
    """Summary over seeds of the time ``key`` (``"wall_s"``, ``"train_s"`` or ``"frames"``) to the threshold.

    Args:
        runs: per seed, ``{"time_to_threshold": {key: value or None}, "curve": [...]}`` as ppo_curves records
            them; a run whose ``time_to_threshold[key]`` is None is censored at its last evaluation's ``key``.
        key: which clock.
        offset_s: a cost paid once before every run (the surrogate's training, s), added to every time.

    Returns:
        ``{"median", "restricted_mean", "reached", "runs", "censored_at", "lower_bound"}``; ``median`` is the
        Kaplan–Meier median (None if not reached by half the runs), ``lower_bound`` True when any run is censored.
    """
    times, reached, censored = [], [], []
    for r in runs:
        t = (r.get("time_to_threshold") or {}).get(key)
        if t is None:
            if not r.get("curve"):
                continue  # the run failed before any evaluation: nothing to censor (its error is recorded)
            t = r["curve"][-1][key]
            censored.append(t + offset_s)
        times.append(t + offset_s)
        reached.append((r.get("time_to_threshold") or {}).get(key) is not None)
    return {"median": km_median(times, reached) if times else None,
            "restricted_mean": sum(times) / len(times) if times else None,
            "reached": sum(reached), "runs": len(times), "censored_at": censored,
            "lower_bound": len(censored) > 0}
