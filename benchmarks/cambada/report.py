"""Tables (markdown, the paper's Tables 3 and 4) and figures (its Figures 5-10) of the results."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from .graph import CRITICAL

SECTION = "## CAMBADA experiment (issue 6)"
LABEL = {
    "monolithic-all": "monolithic loop, every tracker every frame",
    "monolithic": "monolithic loop, trackers at their periods",
    "flowrt": "flowrt",
    "flowrt-rt": "flowrt --realtime",
}
MONO = ("monolithic-all", "monolithic")
REGIME = {
    "calibrated": "paper-calibrated execution times",
    "real": "real trackers on the synthetic scene",
}
LOAD = {"idle": "idle", "load": "2 CPU burners"}
PAPER_NAME = {
    "avoid_fr": "Avoid_Fr",
    "avoid_om": "Avoid_Om",
    "ball_om": "Ball_Om",
    "ball_fr": "Ball_Fr",
    "bgoal": "BGoal",
    "ygoal": "YGoal",
    "line": "Line",
    "bpost": "BPost",
    "ypost": "YPost",
}
TARGET_NORMAL, TARGET_RT = 0.5, 0.1  # ms, std of Avoid_* and Ball_Om
TARGET_TASKS = ("avoid_fr", "avoid_om", "ball_om")


def _f(x: float | None, nd: int = 2) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{nd}f}"


def _rows(res: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {r["task"]: r for r in res["rows"]}


def _find(
    results: list[dict[str, Any]], regime: str, load: str, system: str
) -> dict[str, Any] | None:
    for r in results:
        if (r["regime"], r["load"], r["system"]) == (regime, load, system):
            return r
    return None


def _p1_drops(res: dict[str, Any]) -> int:
    return sum(r["drops"] for r in res["rows"] if r["period"] == 1)


def one_line(res: dict[str, Any]) -> str:
    rows = _rows(res)
    crit = "  ".join(f"{PAPER_NAME[t]} {_f(rows[t]['std'])}" for t in CRITICAL if t in rows)
    extra = f"  [{res.get('granted') or 'normal priority'}]" if res["system"] not in MONO else ""
    return f"    std ms: {crit}   period-1 drops {_p1_drops(res)}{extra}"


# --- tables -------------------------------------------------------------------------------


def task_table(res: dict[str, Any]) -> str:
    """One configuration, the paper's layout: per task max/min/avg/std (ms), drops, misses."""
    fl = res["system"] not in MONO
    head = "| task | period | max | min | avg | std | drops | deadline misses |"
    sep = "|---|---:|---:|---:|---:|---:|---:|---:|"
    if fl:
        head += (
            " flowrt std (dispatch) | flowrt max/min (dispatch) | flowrt skipped | flowrt misses |"
        )
        sep += "---:|---:|---:|---:|"
    lines = [head, sep]
    for r in res["rows"]:
        cells = [
            PAPER_NAME.get(r["task"], r["task"]),
            str(r["period"]),
            _f(r["max"]),
            _f(r["min"]),
            _f(r["mean"]),
            _f(r["std"], 3),
            f"{r['drops']}/{r['expected']}",
            f"{r['misses']}/{r['activations']}",
        ]
        if fl:
            cells += [
                _f(r["fl_std"], 3),
                f"{_f(r['fl_max'])}/{_f(r['fl_min'])}",
                str(r["fl_skipped"]),
                str(r["fl_misses"]),
            ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summary_table(results: list[dict[str, Any]]) -> str:
    head = ["regime", "load", "system"] + [f"{PAPER_NAME[t]} std" for t in CRITICAL]
    head += [
        "critical max/min",
        "period-1 drops",
        "misses (all tasks)",
        "flowrt dispatch std, Avoid/Ball_Om",
        "within 0.3 ms, worst critical",
        "host steal ms",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * 3 + "---:|" * (len(head) - 3)]
    for res in results:
        rows = _rows(res)
        crit = [rows[t] for t in CRITICAL if t in rows]
        mx = max((r["max"] for r in crit if not math.isnan(r["max"])), default=math.nan)
        mn = min((r["min"] for r in crit if not math.isnan(r["min"])), default=math.nan)
        disp = "-"
        if res["system"] not in MONO:
            disp = " / ".join(_f(rows[t]["fl_std"], 3) for t in TARGET_TASKS if t in rows)
        cells = [res["regime"], LOAD[res["load"]], LABEL[res["system"]]]
        cells += [_f(r["std"], 3) for r in crit]
        cells += [
            f"{_f(mx, 1)}/{_f(mn, 1)}",
            str(_p1_drops(res)),
            str(sum(r["misses"] for r in res["rows"])),
            disp,
            _within(crit),
            _f(res.get("steal_ms"), 0),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _within(rows: list[dict[str, Any]], tol: float = 0.3) -> str:
    """The smallest share, over ``rows``, of intervals within ``tol`` ms of the task's median.

    A robust companion to the std: one 3 ms stall in 600 intervals doubles a 0.08 ms std but
    moves this by 0.2 %.
    """
    shares = []
    for r in rows:
        iv = np.asarray(r.get("intervals") or [], dtype=float)
        if len(iv):
            shares.append(float(np.mean(np.abs(iv - np.median(iv)) <= tol)) * 100)
    return f"{min(shares):.1f} %" if shares else "-"


def targets(results: list[dict[str, Any]]) -> tuple[str, list[tuple[str, bool | None]]]:
    """The issue's targets on the paper-calibrated regime, each measured two ways where flowrt
    offers two (its own dispatch-side statistics, and the worker-side start times)."""
    checks: list[tuple[str, str, bool | None]] = []

    def worst(res: dict[str, Any] | None, key: str) -> float | None:
        if res is None:
            return None
        vals = [r[key] for r in res["rows"] if r["task"] in TARGET_TASKS and r[key] is not None]
        return max(vals) if vals else None

    for system, limit in (("flowrt", TARGET_NORMAL), ("flowrt-rt", TARGET_RT)):
        for load in ("idle", "load"):
            res = _find(results, "calibrated", load, system)
            for key, where in (("fl_std", "dispatch (flowrt stats)"), ("std", "worker start")):
                w = worst(res, key)
                checks.append(
                    (
                        f"Avoid_*, Ball_Om std <= {limit} ms, {LABEL[system]}, "
                        f"{LOAD[load]}, {where}",
                        "not run" if w is None else f"worst {w:.3f} ms",
                        None if w is None else w <= limit,
                    )
                )
    for system in ("flowrt", "flowrt-rt"):
        for load in ("idle", "load"):
            res = _find(results, "calibrated", load, system)
            d = None if res is None else _p1_drops(res)
            checks.append(
                (
                    f"no frame dropped by a period-1 task, {LABEL[system]}, {LOAD[load]}",
                    "not run" if d is None else f"{d} dropped",
                    None if d is None else d == 0,
                )
            )
    for load in ("idle", "load"):
        for mono_system in MONO:
            mono = _find(results, "calibrated", load, mono_system)
            for system in ("flowrt", "flowrt-rt"):
                what = (
                    f"{LABEL[mono_system]}: std of Avoid_*, Ball_Om >= 10x {LABEL[system]}'s, "
                    f"{LOAD[load]} (worst task; and task by task)"
                )
                res = _find(results, "calibrated", load, system)
                if mono is None or res is None:
                    checks.append((what, "not run", None))
                    continue
                m, f = _rows(mono), _rows(res)
                worst_m = max(m[t]["std"] for t in TARGET_TASKS)
                worst_f = max(f[t]["std"] for t in TARGET_TASKS)
                ratio = worst_m / max(worst_f, 1e-9)
                each = {t: m[t]["std"] / max(f[t]["std"], 1e-9) for t in TARGET_TASKS}
                text = f"worst {ratio:.0f}x ({worst_m:.2f} vs {worst_f:.3f} ms); " + ", ".join(
                    f"{PAPER_NAME[t]} {x:.1f}x" for t, x in each.items()
                )
                checks.append((what, text, ratio >= 10))
                if ratio >= 10 and min(each.values()) < 10:
                    checks[-1] = (what, text + " — not every task", True)
    lines = ["| target (paper-calibrated regime) | measured | met |", "|---|---|---|"]
    for what, measured, ok in checks:
        lines.append(
            f"| {what} | {measured} | {'-' if ok is None else ('yes' if ok else '**no**')} |"
        )
    return "\n".join(lines), [(w, ok) for w, _, ok in checks]


# --- figures ------------------------------------------------------------------------------


def figures(
    results: list[dict[str, Any]], mode: dict[str, Any] | None, out: Path
) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    made: dict[str, Path] = {}
    for regime in ("calibrated", "real"):
        for load in ("idle", "load"):
            runs = [
                r for s in (*MONO, "flowrt", "flowrt-rt") if (r := _find(results, regime, load, s))
            ]
            if not runs:
                continue
            fig, axes = plt.subplots(2, len(runs), figsize=(4.2 * len(runs), 6.2), squeeze=False)
            for col, res in enumerate(runs):
                rows = _rows(res)
                for row, task in enumerate(("avoid_om", "ball_om")):
                    ax = axes[row][col]
                    r = rows[task]
                    iv = r["intervals"]
                    if iv:
                        lo, hi = min(iv), max(iv)
                        if hi - lo < 4:  # a tight distribution: 0.05 ms bins around 50
                            lo, hi = min(lo, 48.0), max(hi, 52.0)
                        bins = max(20, min(200, int((hi - lo) / 0.05) if hi - lo < 4 else 100))
                        ax.hist(
                            iv,
                            bins=bins,
                            range=(lo, hi),
                            color="tab:red" if res["system"] in MONO else "tab:blue",
                        )
                    ax.set_yscale("log")
                    ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
                    ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
                    ax.set_title(
                        f"{PAPER_NAME[task]} — {LABEL[res['system']]}\n"
                        f"avg {_f(r['mean'])} std {_f(r['std'], 3)} "
                        f"min {_f(r['min'])} max {_f(r['max'])} ms",
                        fontsize=8,
                    )
                    ax.set_xlabel("inter-activation time (ms)", fontsize=8)
                    ax.set_ylabel("activations", fontsize=8)
                    ax.tick_params(labelsize=7)
            fig.suptitle(
                f"CAMBADA inter-activation times: {REGIME[regime]}, {LOAD[load]}", fontsize=10
            )
            fig.tight_layout()
            path = out / f"cambada_hist_{regime}_{load}.png"
            fig.savefig(path, dpi=90)
            plt.close(fig)
            made[f"{regime}/{load}"] = path
    if mode is not None:
        fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        for ax, node, before, after in ((axes[0], "ball_fr", 50, 100), (axes[1], "line", 400, 50)):
            s = mode["series"][node]
            ax.plot(s["t"], s["interval"], ".-", ms=3, lw=0.6, color="tab:blue")
            ax.axvline(mode["switch"], color="tab:red", ls="--", lw=1)
            ax.set_yscale("log")
            ax.set_ylim(20, 1000)
            ax.set_yticks([25, 50, 100, 200, 400, 800])
            ax.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
            ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            ax.text(
                mode["switch"],
                900,
                " set_mode('paper_mode_change')",
                color="tab:red",
                fontsize=8,
                va="top",
            )
            ax.grid(True, which="major", axis="y", lw=0.3)
            ax.set_ylabel("inter-activation (ms)", fontsize=8)
            ax.set_title(f"{PAPER_NAME[node]}: period {before} ms -> {after} ms", fontsize=9)
        axes[1].set_xlabel("time since start (s)", fontsize=8)
        fig.suptitle(
            "CAMBADA mode change under flowrt (paper-calibrated, idle, "
            f"{mode['granted'] or 'normal priority'})",
            fontsize=10,
        )
        fig.tight_layout()
        path = out / "cambada_mode_change.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        made["mode"] = path
    return made


def mode_numbers(mode: dict[str, Any]) -> str:
    lines = ["| task | before: mean / std / n | after: mean / std / n |", "|---|---:|---:|"]
    import numpy as np

    for node in ("ball_fr", "line", "ball_om"):
        s = mode["series"][node]
        t, iv = np.asarray(s["t"]), np.asarray(s["interval"])
        cells = []
        for sel in (t < mode["switch"] - 0.5, t > mode["switch"] + 1.0):  # leave the transition out
            x = iv[sel & (t > 1.0)]
            cells.append(
                f"{x.mean():.2f} / {x.std(ddof=1):.3f} / {len(x)}"
                if len(x) > 1
                else f"- / - / {len(x)}"
            )
        lines.append(f"| {PAPER_NAME[node]} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines)


# --- the markdown section -----------------------------------------------------------------


def observations(results: list[dict[str, Any]]) -> str:
    """What the figures say next to the paper's, computed from this run."""
    out = []

    def span(res: dict[str, Any], tasks: tuple[str, ...], key: str) -> tuple[float, float]:
        vals = [r[key] for r in res["rows"] if r["task"] in tasks and not math.isnan(r[key])]
        return (min(vals), max(vals)) if vals else (math.nan, math.nan)

    parts = []
    for load in ("idle", "load"):
        m = _find(results, "calibrated", load, "monolithic-all")
        if m is not None:
            lo, hi = span(m, CRITICAL, "min")[0], span(m, CRITICAL, "max")[1]
            b = _rows(m)["ball_om"]
            parts.append(
                f"{lo:.0f}-{hi:.0f} ms {LOAD[load]} (Ball_Om ran on {b['expected'] - b['drops']} "
                f"of {b['expected']} frames)"
            )
    if parts:
        out.append(
            "- paper, monolithic: 17-197 ms, frames skipped. Ours, every tracker on every frame "
            "(paper-calibrated), critical tasks: " + "; ".join(parts) + "."
        )
    parts = []
    for load in ("idle", "load"):
        f = _find(results, "calibrated", load, "flowrt-rt")
        if f is not None:
            s_lo, s_hi = span(f, TARGET_TASKS, "std")
            s_fr = _rows(f).get("ball_fr", {}).get("std", math.nan)
            mean_lo, mean_hi = span(f, CRITICAL, "mean")
            parts.append(
                f"{LOAD[load]}: avg {mean_lo:.2f}-{mean_hi:.2f} ms, std {s_lo:.3f}-{s_hi:.3f} ms "
                f"for Avoid_* and Ball_Om, {s_fr:.2f} ms for Ball_Fr, {_p1_drops(f)} frame drops"
            )
    if parts:
        out.append(
            "- paper, modular (PMan): 50 ms average, std 0.5-2.1 ms for the critical tasks, no "
            "frame drop. flowrt --realtime (paper-calibrated): " + "; ".join(parts) + ". Ball_Fr "
            "(priority 35) waits, by design, while the higher-priority omni tasks hold both CPUs."
        )
    f = _find(results, "calibrated", "idle", "flowrt") or _find(
        results, "calibrated", "load", "flowrt"
    )
    if f is not None:
        granted = ", ".join(
            f"{PAPER_NAME[n]} {g}" for n, g in f.get("workers", {}).items() if n in PAPER_NAME and g
        )
        worst = []
        for load in ("idle", "load"):
            r = _find(results, "calibrated", load, "flowrt")
            if r is not None:
                worst.append(
                    f"{LOAD[load]}: Ball_Om std {_rows(r)['ball_om']['std']:.2f} ms, "
                    f"{_p1_drops(r)} frame drops"
                )
        out.append(
            "- flowrt without --realtime (paper-calibrated): " + "; ".join(worst) + ". The "
            f"workers' OS priorities are nice levels by rank ({granted}), the event loop at "
            f"{f.get('granted') or 'nice 0'}: the fair scheduler shares the CPUs by weight and "
            "wakes a task that used more than its share only at its next tick (4 ms here, "
            "see benchmarks/bench_fair_wakeup.py), instead of preempting by priority."
        )
    return "\n".join(out)


def markdown(
    results: list[dict[str, Any]],
    mode: dict[str, Any] | None,
    figs: dict[str, Path],
    meta: dict[str, Any],
    *,
    fig_base: Path,
) -> str:
    def rel(p: Path) -> str:
        try:
            return str(p.relative_to(fig_base))
        except ValueError:
            return str(p)

    tgt, _ = targets(results)
    out = [SECTION, ""]
    out.append(
        f"Command: `{meta['command']}` ({meta['duration']:g} s per run, {len(results)} runs"
        + (f", mode change {meta['mode_duration']:g} s" if mode else "")
        + "; `--quick` for a 2-minute smoke run, `--help` for the options)."
    )
    out.append(
        f"Measured {meta['date']} on {meta['machine']}. The machine was shared with other "
        "engineers' test runs (some of them SCHED_FIFO benchmarks), so a figure may carry their "
        "noise; the raw records of every run are kept in the output directory the command prints."
    )
    out.append("")
    out.append("""What runs (benchmarks/cambada/):

- the same deterministic frames (graphs/cambada.yaml's two synthetic cameras, seeds 1 and 2,
  20 fps, the omni camera half a frame after the front one) through
  - **monolithic loop**: one process per camera, as the paper's Frontvision (Avoid_Fr, Ball_Fr)
    and Omnivision (the other seven), at normal priority — it takes the newest frame delivered
    (waiting for the next one if none is new; frames overtaken while it was busy are skipped),
    renders it, then runs its trackers in sequence (flowrt's dispatch order): *every tracker on
    every frame* (the paper's original processes), or only the *due* ones (each task's
    period/phase in frames, as in the graph: the same workload as flowrt);
  - **flowrt**: the graph via `flowrt run GRAPH --no-ui --log-every 3600 --duration S
    --stats-json F --spin 300us [--realtime]`, nine trackers in worker processes. GRAPH is
    graphs/cambada.yaml with its timing and worker options untouched (the four period-1
    trackers pinned two per CPU, each ball tracker with the other camera's obstacle tracker,
    and spinning 300 us around each expected activation), the display node dropped (a web
    server has no place in a timing benchmark), the trackers' kind replaced by recording (or
    calibrated) subclasses and, with `--capture ahead` (the default), the cameras' by
    `AheadCapture`: the built-in capture node publishing the same frames, but with the scene's
    motion simulated at setup (the built-in one simulates it on frames 0, 256, 512..., ~2 ms
    more on those) and each frame rendered into its frame slot 10 ms after the previous tick
    instead of at its own (a render takes 0.5-1.5 ms, varying with content and cache state);
    so the tick follows the timer by a constant, as with a camera that has written its frame
    into memory, and the figures show the scheduler, not the synthetic scene. `--spin 300us`:
    the loop wakes 300 us before each tick and busy-waits the rest, because a CPU woken from
    idle in this VM takes 0.05-0.2 ms, different every time. Without `--realtime` flowrt gives
    the loop the lowest nice level permitted and the workers nice levels by priority rank
    (root here: -20 for the loop, -17 .. -2 for the trackers). The monolithic loop renders
    its next frame right after a frame's work. `--capture builtin` keeps the built-in node.
    The periodic `--no-ui` summary lines are off: each computes the statistics on the event
    loop (~1 ms), at an instant that falls on the omni camera's tick;
- two execution-time regimes: the real `tracker` nodes (colour tracking of the synthetic scene,
  mostly < 1 ms), and paper-calibrated trackers burning CPU time (not sleeping) drawn per (task,
  frame) from a seeded RNG, so both architectures burn the same time on the same frame: Avoid
  1-5 ms; Ball < 5 ms w.p. 0.761 and 25-35 ms w.p. 0.139 (the paper), the remaining 10 % split
  by us as 5-25 ms w.p. 0.09 and 35-38.75 ms w.p. 0.01 (max 38.75 as in the paper); goals 4-10
  ms, Line 8-16 ms, posts 2-6 ms (our choice: not in the paper's summary);
- each idle and beside 2 processes spinning `while True: pass` at normal priority.

*Host steal*: CPU time the hypervisor took from this VM during the run (``/proc/stat``),
when not 0 a stall no scheduling inside the VM can prevent.
*Within 0.3 ms*: the smallest share, over the critical tasks, of intervals within 0.3 ms of
the task's median interval: a robust companion to the std, which one 3 ms stall in 600
intervals doubles.

Columns: inter-activation max/min/avg/std (ms) from the start times each tracker records in the
process that runs it (a flowrt worker, or the loop), first second of the run left out; *drops*:
frames on which a task was due but did not run / frames due; *deadline misses*: finished later
than the graph's deadline after the frame's release / activations. For flowrt, its own
`--stats-json` figures too: `interval` measured on the event loop at dispatch (whole run),
`skipped` and `deadline_misses`. Deadline misses in the calibrated regime mostly mean that the
paper's execution time (Ball up to 38.75 ms) exceeds the graph's deadline (Ball_Om 15 ms,
Ball_Fr 20 ms), not lateness.
""")
    out.append("""The paper's figures (as summarised in issue 6; its per-task Tables 3 and 4 are not
reproduced here):

| architecture | inter-activation time | frame drops |
|---|---|---|
| monolithic (Frontvision/Omnivision) | 17-197 ms | frames skipped |
| modular (PMan: prioritised periodic tasks) | 50 ms avg, std 0.5-2.1 ms (critical tasks) | none |
""")
    out += ["### Targets", "", tgt, ""]
    obs = observations(results)
    if obs:
        out += ["### Beside the paper", "", obs, ""]
    for system, title in (
        ("monolithic-all", "Table 3 — monolithic loop, every tracker on every frame"),
        ("monolithic", "Table 3b — monolithic loop, trackers at their periods"),
        ("flowrt", "Table 4 — flowrt"),
        ("flowrt-rt", "Table 4b — flowrt --realtime"),
    ):
        res = _find(results, "calibrated", "idle", system)
        if res is not None:
            out += [f"### {title} (paper-calibrated, idle)", "", task_table(res), ""]
    out += [
        "### Every configuration: critical tasks (std in ms, worker/loop start times)",
        "",
        summary_table(results),
        "",
    ]
    for key, path in figs.items():
        if key != "mode":
            out.append(f"![inter-activation histograms {key}]({rel(path)})")
    out.append("")
    if mode is not None:
        out += ["### Mode change (paper Figures 9-10)", ""]
        out.append(
            f"`rt.set_mode('paper_mode_change')` {mode['switch']:.1f} s into a paper-calibrated "
            f"idle run ({mode['granted'] or 'normal priority'}): Ball_Om disabled, Ball_Fr every 2 "
            "frames, Line every frame at priority 40. Intervals from the workers' start times "
            "(transition +-1 s left out):"
        )
        out += ["", mode_numbers(mode), ""]
        if "mode" in figs:
            out.append(f"![mode change]({rel(figs['mode'])})")
            out.append("")
    out += ["<details><summary>Per-task tables of every configuration</summary>", ""]
    for res in results:
        granted = f" ({res['granted']})" if res.get("granted") else ""
        out += [
            f"#### {REGIME[res['regime']]}, {LOAD[res['load']]}, {LABEL[res['system']]}{granted}",
            "",
            task_table(res),
            "",
        ]
    out += ["</details>", ""]
    return "\n".join(out)


def update_results(path: Path, section: str) -> None:
    """Replace this experiment's section of RESULTS.md (or append it); leave others alone."""
    text = path.read_text() if path.exists() else "# Benchmark results\n"
    pattern = re.compile(re.escape(SECTION) + r".*?(?=^## |\Z)", re.S | re.M)
    if pattern.search(text):
        text = pattern.sub(lambda _: section.rstrip() + "\n\n", text, count=1)
    else:
        text = text.rstrip() + "\n\n" + section.rstrip() + "\n"
    path.write_text(text)


def summary(results: list[dict[str, Any]]) -> str:
    return "\n" + summary_table(results) + "\n\n" + targets(results)[0] + "\n"
