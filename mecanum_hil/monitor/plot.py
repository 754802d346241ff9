"""PNG of a shadow run: measured wheel speeds against the model, alarms marked."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..io.recording import Recording
from ..plots import save_figure


def plot_shadow(measured: Recording, model: Recording, alarms: Sequence, path: str | Path,
                title: str = "", fault_t_s: float | None = None) -> Path:
    """Wheel speeds (measured dots, model lines) and residuals, one colour per wheel.

    Parameters
    ----------
    measured, model : Recording
        The run and the model's prediction for its commands (same ``t_s``).
    alarms : sequence of Alarm
        Drawn as vertical lines, labelled with their channel.
    path : str or Path
        PNG to write.
    fault_t_s : float, optional
        A known fault time (demo), drawn dashed.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_w, ax_r) = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    t = measured.t_s
    for i in range(4):
        y = measured.wheel_rpm[:, i]
        if not np.isfinite(y).any():
            continue
        ax_w.plot(t, y, ".", color=colours[i], ms=1.5, label=f"wheel {i + 1} measured")
        ax_w.plot(model.t_s, model.wheel_rpm[:, i], "-", color=colours[i], lw=1.0,
                  label=f"wheel {i + 1} model")
        ax_r.plot(t, y - model.wheel_rpm[:, i], "-", color=colours[i], lw=0.7,
                  label=f"wheel {i + 1}")
    for ax in (ax_w, ax_r):
        if fault_t_s is not None:
            ax.axvline(fault_t_s, color="k", ls="--", lw=1.0)
        for a in alarms:
            ax.axvline(a.t_s, color="r", lw=1.0, alpha=0.7)
        ax.grid(True, alpha=0.3)
    _label_alarms(ax_r, alarms, t)
    ax_w.set_ylabel("wheel speed [rpm]")
    ax_w.legend(fontsize=8, ncol=4)
    ax_r.set_ylabel("measured - model [rpm]")
    ax_r.set_xlabel("t [s]")
    ax_r.legend(fontsize=8, ncol=4)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi=110)


def _label_alarms(ax, alarms: Sequence, t: np.ndarray, most: int = 4) -> None:
    """One label per group of alarms close in time (within 3 % of the run), listing the
    group's channels, in a box at the top of ``ax``: alarms a few samples apart would
    otherwise stack their labels into one block. At most ``most`` groups are labelled."""
    if not alarms:
        return
    span = float(np.nanmax(t) - np.nanmin(t)) if np.isfinite(t).any() else 1.0
    groups: list[list] = []
    for a in sorted(alarms, key=lambda a: a.t_s):
        if groups and a.t_s - groups[-1][0].t_s <= 0.03 * span:
            groups[-1].append(a)
        else:
            groups.append([a])
    lo, hi = ax.get_xlim()
    for k, group in enumerate(groups[:most]):
        channels = list(dict.fromkeys(a.channel for a in group))
        text = f"alarm at {group[0].t_s:.2f} s: " + ", ".join(channels)
        x = group[0].t_s
        right = x > lo + 0.6 * (hi - lo)  # near the right edge: the label to the left
        ax.annotate(text, (x, 1.0), xycoords=("data", "axes fraction"),
                    xytext=(-4 if right else 4, -4 - 16 * k), textcoords="offset points",
                    ha="right" if right else "left", va="top", fontsize=9, color="r",
                    bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "r", "alpha": 0.9})
    if len(groups) > most:
        ax.annotate(f"(+{len(groups) - most} more alarm groups)", (0.99, 0.02),
                    xycoords="axes fraction", ha="right", va="bottom", fontsize=8, color="r")
