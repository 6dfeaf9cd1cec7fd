"""Turn a benchmark result into what people read: the terminal table and summary here; PNG
plots (plots.py) and BENCHMARKS.md (markdown.py), whose writers callers also import from here.

Owns: the layout of the headline table and of the summary `softplc bench` prints.
Reads only the result dictionary.
Does not know: how anything was measured.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from softplc.bench.cells import fmt, verdict, with_unit
from softplc.bench.markdown import REPORTED
from softplc.bench.markdown import write_markdown as write_markdown
from softplc.bench.plots import write_plots as write_plots


def _bound(row: dict[str, Any]) -> str:
    op, _, bound = str(row["target"]).partition(" ")
    unit = row.get("unit", "x")
    return f"{op} {bound}x" if unit == "x" else f"{op} {bound}"


def headline_table(results: dict[str, Any]) -> str:
    """The headline figures: value with its unit (x: a ratio, times), the target, the verdict,
    the scan period it was measured at and what it means."""
    rows = [(r["key"], with_unit(r["value"], r.get("unit", "x")), _bound(r),
             verdict(r["met"]), r.get("period") or "-", r["meaning"]) for r in results["targets"]]
    rss = results["headline"].get("memory.rss_mb")
    memory = results.get("sections", {}).get("memory", {})
    period = f"{memory['period_ms']} ms" if isinstance(memory, dict) and "period_ms" in memory \
        else "-"
    rows.append(("memory.rss_mb", with_unit(rss, "MB"), "-", "reported", period,
                 "resident memory of the scan, communication and compile processes after the soak "
                 "(4 Modbus clients + HTTP)"))
    rows += [(key, with_unit(results["headline"].get(key), unit), "-", "reported", "10 ms", meaning)
             for key, unit, meaning in REPORTED]
    head = ("figure", "value", "target", "verdict", "period", "meaning")
    widths = [max(len(str(r[i])) for r in [head, *rows]) for i in range(5)]
    return "\n".join("  ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=False))
                     + "  " + r[5] for r in [head, *rows])


def summary(results: dict[str, Any], written: Sequence[str] = ()) -> str:
    """What `softplc bench` prints at the end: what ran, on what, the table, the verdict, and
    where the full story is."""
    machine = results.get("machine", {})
    seconds = results.get("seconds", {})
    quick = results.get("mode") == "quick"
    targets = [t for t in results["targets"] if t["met"] is not None]
    missed = [t["key"] for t in targets if not t["met"]]
    load = machine.get("load_average", [None])[0]
    lines = [
        f"softplc bench ({results.get('mode')}): {len(seconds)} section(s) in "
        f"{sum(seconds.values()):.0f} s on {machine.get('cpu')} ({machine.get('cores')} cores, "
        f"load {fmt(load)} at start)",
        "Ratios (x) compare with a baseline measured in the same run on this machine, so "
        "they hold across machines better than raw times; period = the PLC scan period.",
        "",
        headline_table(results),
        "",
        f"verdict: {len(targets) - len(missed)} of {len(targets)} measured target(s) met"
        + (f"; missed: {', '.join(missed)}" if missed else "")
        + (f"; not measured: {len(results['targets']) - len(targets)}"
           if len(targets) < len(results["targets"]) else ""),
    ]
    if quick:
        lines.append("quick mode: small sizes and short runs, figures are indicative; a shared "
                     "or loaded machine misses the 1 ms targets more often.")
    lines.append("what each figure measures, how, and why a target can be missed: BENCHMARKS.md "
                 "(`make bench` regenerates it from a full run)"
                 + (f"; this run written to {', '.join(written)}" if written else ""))
    return "\n".join(lines)
