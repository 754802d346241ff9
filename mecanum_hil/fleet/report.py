"""``fleet-report``: which robots drifted and how, as PNG plots and a Markdown summary."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..io.paths import staged_folder
from .results import add_drift

_COEFFS = (("A", "1/s"), ("B", "1/s"), ("C", "1/s^2"))


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "robot"


def _num(v: Any, fmt: str = ".4g") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else \
        format(v, fmt)


def _by_group(rows: Sequence[Mapping[str, Any]]) -> dict[str, list[Mapping[str, Any]]]:
    out: dict[str, list[Mapping[str, Any]]] = {}
    for r in sorted(rows, key=lambda r: (r["group"] or "", r["period"] or "")):
        out.setdefault(r["group"] or "", []).append(r)
    return out


def plot_trends(rows: Sequence[Mapping[str, Any]], path: Path, title: str) -> Path | None:
    """A, B, C per period, one line per robot; drifted robots in colour, the others grey."""
    from ..plots import _pyplot, save_figure

    fitted = [r for r in rows if r["A"] is not None and r["status"] in ("ok", "partial")]
    if not fitted:
        return None
    plt = _pyplot()
    periods = sorted({r["period"] or "" for r in fitted})
    x_of = {p: i for i, p in enumerate(periods)}
    groups = _by_group(fitted)
    drifted = {g for g, rs in groups.items() if any(r["drifted"] for r in rs)}
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4), squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for j, (k, unit) in enumerate(_COEFFS):
        ax = axes[0, j]
        n_colour = 0
        for g, rs in groups.items():
            xs = [x_of[r["period"] or ""] for r in rs]
            ys = [r[k] for r in rs]
            if g in drifted:
                c = colours[n_colour % len(colours)]
                n_colour += 1
                lo = [r[k] - r[f"{k}_lo"] if r[f"{k}_lo"] is not None else 0.0 for r in rs]
                hi = [r[f"{k}_hi"] - r[k] if r[f"{k}_hi"] is not None else 0.0 for r in rs]
                ax.errorbar(xs, ys, yerr=[lo, hi], fmt="o-", color=c, lw=1.6, ms=4,
                            capsize=3, label=g)
                for r, x, y in zip(rs, xs, ys, strict=True):
                    if r["effects_appeared"]:
                        ax.annotate("+" + r["effects_appeared"], (x, y), fontsize=7,
                                    xytext=(4, 4), textcoords="offset points", color=c)
            else:
                ax.plot(xs, ys, "-", color="0.7", lw=0.8, marker=".", ms=3)
        ax.set_xticks(range(len(periods)))
        ax.set_xticklabels([p or "(all)" for p in periods], rotation=30, ha="right",
                           fontsize=8)
        ax.set_ylabel(f"{k} [{unit}]")
        ax.set_title(f"{k} per period ({len(groups)} robots, {len(drifted)} drifted)",
                     fontsize=10)
        ax.grid(True, alpha=0.3)
        if drifted and j == 0:
            ax.legend(fontsize=7, title="drifted", title_fontsize=7)
    fig.suptitle(title, fontsize=11)
    return save_figure(fig, path)


def plot_robot(rows: Sequence[Mapping[str, Any]], path: Path, group: str) -> Path:
    """One robot: A, B, C per period with their 95 % intervals, effects named per period."""
    from ..plots import _pyplot, save_figure

    plt = _pyplot()
    rs = [r for r in rows if r["A"] is not None]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), squeeze=False)
    xs = list(range(len(rs)))
    for j, (k, unit) in enumerate(_COEFFS):
        ax = axes[0, j]
        ys = [r[k] for r in rs]
        lo = [r[k] - r[f"{k}_lo"] if r[f"{k}_lo"] is not None else 0.0 for r in rs]
        hi = [r[f"{k}_hi"] - r[k] if r[f"{k}_hi"] is not None else 0.0 for r in rs]
        ax.errorbar(xs, ys, yerr=[lo, hi], fmt="o-", capsize=3)
        for r, x, y in zip(rs, xs, ys, strict=True):
            if r["drifted"]:
                ax.plot([x], [y], "o", ms=11, mfc="none", mec="red")
            if r["effects"] and j == 0:
                ax.annotate(r["effects"], (x, y), fontsize=7, xytext=(4, -10),
                            textcoords="offset points")
        ax.set_xticks(xs)
        ax.set_xticklabels([r["period"] or "(all)" for r in rs], rotation=30, ha="right",
                           fontsize=8)
        ax.set_ylabel(f"{k} [{unit}]")
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"{group}: coefficients per period (red ring: drifted)", fontsize=11)
    return save_figure(fig, path)


def plot_alarms(rows: Sequence[Mapping[str, Any]], path: Path) -> Path | None:
    """Shadow alarms per robot (stacked over periods)."""
    from ..plots import _pyplot, save_figure

    groups = _by_group([r for r in rows if r["alarms"] is not None])
    if not groups:
        return None
    plt = _pyplot()
    names = list(groups)
    counts = [sum(r["alarms"] or 0 for r in groups[g]) for g in names]
    fig, ax = plt.subplots(figsize=(max(5.0, 0.35 * len(names) + 2), 3.8))
    ax.bar(range(len(names)), counts, color=["tab:red" if c else "0.7" for c in counts])
    ax.set_xticks(range(len(names)))
    ax.set_xticklabels(names, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("shadow alarms")
    ax.set_title("shadow replay: alarms per robot")
    return save_figure(fig, path)


def write_report(rows: Sequence[Mapping[str, Any]], out_dir: str | Path,
                 source: str = "results", min_relative: float | None = None) -> dict[str, Path]:
    """Write ``summary.md`` and the PNG plots into ``out_dir``.

    Parameters
    ----------
    rows : sequence of dict
        A results table (:func:`~.results.read_results`).
    out_dir : str or Path
    source : str
        Name of the table, for the summary.
    min_relative : float, optional
        Recompute the drift with this threshold [-] (default: as written in the table).

    Returns
    -------
    dict
        ``{"summary": path, "trends": path, ...}`` of the files written.
    """
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:  # a file of that name (FileExistsError), no permission ...
        raise ConfigError(f"{out}: cannot make the report folder: "
                          f"{err.strerror or err}") from err
    with staged_folder(out, last=("summary.md",)) as stage:  # seen whole or not at all
        written = _write_files(rows, stage, source, min_relative)
    return {key: out / p.name for key, p in written.items()}


def _write_files(rows: Sequence[Mapping[str, Any]], out: Path, source: str,
                 min_relative: float | None) -> dict[str, Path]:
    """The report's files, written into ``out`` (the staging folder)."""
    table = add_drift(rows, min_relative) if min_relative is not None else \
        sorted(rows, key=lambda r: (r["group"] or "", r["period"] or ""))
    written: dict[str, Path] = {}
    commands = sorted({r["command"] for r in table if r["command"]})
    groups = _by_group(table)
    periods = sorted({r["period"] for r in table if r["period"]})
    status = {s: sum(1 for r in table if r["status"] == s) for s in ("ok", "partial", "failed")}
    drifted_rows = [r for r in table if r["drifted"]]
    drifted = sorted({r["group"] for r in drifted_rows})
    trends = plot_trends(table, out / "trends.png", f"{source}: coefficient trends")
    if trends:
        written["trends"] = trends
    for g in drifted:
        written[f"robot:{g}"] = plot_robot(groups[g], out / f"robot-{_safe(g)}.png", g)
    alarms = plot_alarms(table, out / "alarms.png") if "shadow" in commands else None
    if alarms:
        written["alarms"] = alarms
    lines = [f"# Fleet report: {source}", "",
             f"Batch {', '.join(commands) or '-'}: {len(groups)} robot(s), "
             f"{len(periods)} period(s), {len(table)} row(s): {status['ok']} ok, "
             f"{status['partial']} with inputs left out, {status['failed']} failed.", ""]
    if any(r["A"] is not None for r in table):
        lines += [f"**Drifted: {len(drifted)} robot(s)**" + (f": {', '.join(drifted)}"
                                                              if drifted else ""), ""]
    if drifted_rows:
        lines += ["## What changed", "",
                  "A coefficient counts as drifted when its change since the robot's previous "
                  "period is outside both 95 % intervals combined and at least the relative "
                  "threshold; an effect named now and not before (or the reverse) counts too.",
                  "", "| robot | period | change | A | B | C | effects |",
                  "|---|---|---|---|---|---|---|"]
        for r in drifted_rows:
            lines.append(f"| {r['group']} | {r['period'] or '-'} | {r['drift_note']} | "
                         f"{_num(r['A'])} | {_num(r['B'])} | {_num(r['C'])} | "
                         f"{r['effects'] or '-'} |")
        lines.append("")
        lines += [f"![{g}](robot-{_safe(g)}.png)" for g in drifted] + [""]
    appeared = [r for r in table if r["effects_appeared"]]
    if appeared:
        lines += ["## Effects that appeared", ""]
        lines += [f"- {r['group']} ({r['period'] or '-'}): {r['effects_appeared']}"
                  for r in appeared]
        lines.append("")
    if trends:
        lines += ["## Trends", "", "![trends](trends.png)", ""]
    if any(r["A"] is not None for r in table):
        lines += ["## Latest model per robot", "",
                  "| robot | period | A [1/s] (95 %) | B [1/s] (95 %) | C [1/s^2] (95 %) | "
                  "effects | RMSE [rpm] |", "|---|---|---|---|---|---|---|"]
        for g, rs in groups.items():
            good = [r for r in rs if r["A"] is not None]
            if not good:
                continue
            r = good[-1]
            cells = [f"{_num(r[k])} [{_num(r[k + '_lo'])}, {_num(r[k + '_hi'])}]"
                     for k in ("A", "B", "C")]
            lines.append(f"| {g} | {r['period'] or '-'} | " + " | ".join(cells)
                         + f" | {r['effects'] or '-'} | {_num(r['rmse_rpm'], '.3g')} |")
        lines.append("")
    if alarms:
        alarmed = [r for r in table if (r["alarms"] or 0) > 0]
        lines += ["## Shadow alarms", "", "| robot | period | alarms | recordings | first [s] |",
                  "|---|---|---|---|---|"]
        lines += [f"| {r['group']} | {r['period'] or '-'} | {r['alarms']} | "
                  f"{r['alarm_inputs'] or '-'} | {_num(r['first_alarm_t_s'], '.3f')} |"
                  for r in alarmed] or ["| - | - | 0 | - | - |"]
        lines += ["", "![alarms](alarms.png)", ""]
    bad = [r for r in table if r["status"] in ("failed", "partial")]
    if bad:
        lines += ["## Failed groups and inputs left out", ""]
        lines += [f"- {r['group']} {r['period'] or ''} ({r['status']}): {r['error']}"
                  for r in bad]
        lines.append("")
    summary = out / "summary.md"
    summary.write_text("\n".join(lines), encoding="utf-8")
    written["summary"] = summary
    return written
