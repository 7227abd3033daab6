"""The latest results in one place: ``summary.md`` (every table, with the
machine) and ``bench.png`` (latency, recorder rate, fault times), from the
JSON files the benchmarks left in the results folder."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from bodynet.bench import machine

SECTIONS = (
    ("decode", "Decode rates, each beside a bare baseline"),
    ("solver", "Gateway tick work per body, bodies solved together against one at a time"),
    ("gateway", "Gateway beside a bare Zenoh relay, 15 nodes x 100 Hz per body"),
    ("peer", "Against Lab Streaming Layer, same stream, same run"),
    ("rate", "One body at the rate of `--rate-hz` per node"),
    ("recorder", "Recorder against the bare mcap writer"),
    ("faults", "Faults: time to see them or recover"),
    ("soak", "Soak: one body through gateway and recorder"),
    ("drift", "Calibration on real frames: the subject facing anywhere, 6-axis drift"),
    ("truth", "Poses against the truth: emulated sessions through `bodynet process`"),
)


def _load(out_dir: Path, name: str) -> dict[str, Any] | None:
    path = out_dir / f"{name}.json"
    try:
        data: dict[str, Any] = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data


def _plot(out_dir: Path, results: dict[str, dict[str, Any]]) -> Path | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [n for n in ("peer", "recorder", "faults") if n in results]
    if "rate" in results and "peer" not in panels:
        panels.insert(0, "rate")
    if not panels:
        return None
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.2), squeeze=False)
    for ax, name in zip(axes[0], panels, strict=True):
        r = results[name]
        if name in ("peer", "rate"):
            bars: list[tuple[str, float, float]] = []
            if name == "peer":
                bars += [("LSL\n1 hop", r["lsl_one_hop"]["p50_ms"], r["lsl_one_hop"]["p99_ms"]),
                         ("relay\n2 hops", r["zenoh_relay_two_hops"]["p50_ms"],
                          r["zenoh_relay_two_hops"]["p99_ms"]),
                         ("gateway\n2 hops", r["gateway_two_hops"]["p50_ms"],
                          r["gateway_two_hops"]["p99_ms"])]  # fmt: skip
            if "rate" in results:
                g = results["rate"]["gateway"]
                hz = results["rate"]["rate_hz_per_node"]
                bars.append((f"gateway\n{hz:g} Hz/node", g["p50_ms"], g["p99_ms"]))
            x = range(len(bars))
            ax.bar([i - 0.2 for i in x], [b[1] for b in bars], 0.4, label="p50")
            ax.bar([i + 0.2 for i in x], [b[2] for b in bars], 0.4, label="p99")
            ax.set_xticks(list(x), [b[0] for b in bars])
            ax.set_ylabel("latency, ms")
            ax.set_title("raw sample to output")
            ax.legend()
        elif name == "recorder":
            rows = r["rows"]
            x = range(len(rows))
            ax.bar([i - 0.2 for i in x], [row["baseline_per_s"] for row in rows], 0.4,
                   label="bare mcap writer")  # fmt: skip
            ax.bar([i + 0.2 for i in x], [row["bodynet_per_s"] for row in rows], 0.4,
                   label="bodynet McapSink")  # fmt: skip
            ax.set_xticks(list(x), ["raw samples", "body poses"])
            ax.set_yscale("log")
            ax.set_ylabel("messages / s")
            ax.set_title(f"recorder (live: {r['recorder_live']['per_s']:,.0f} raw/s)")
            ax.legend()
        else:
            rows = [row for row in r["rows"] if not math.isnan(row["worst_s"])]
            y = range(len(rows))
            ax.barh(list(y), [max(row["worst_s"], 1e-4) for row in rows], label="measured (worst)")
            for i, row in enumerate(rows):
                if row["target_s"] is not None:
                    ax.plot(row["target_s"], i, "k|", markersize=18,
                            label="target" if i == 0 or "target" not in
                            ax.get_legend_handles_labels()[1] else None)  # fmt: skip
            ax.set_yticks(list(y), [row["fault"].split(":")[0] + ":\n" +
                                    row["fault"].split(":", 1)[-1].strip() for row in rows],
                          fontsize=7)  # fmt: skip
            ax.set_xscale("log")
            ax.set_xlabel("seconds")
            ax.set_title("faults")
            ax.legend(fontsize=7)
    fig.suptitle(machine.line(), fontsize=8)
    fig.tight_layout()
    path = out_dir / "bench.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write(out_dir: Path) -> Path:
    """``summary.md`` and ``bench.png`` in ``out_dir`` from what is there; returns the summary."""
    results = {n: r for n, _ in SECTIONS if (r := _load(out_dir, n)) is not None}
    parts = [f"# bodynet benchmarks\n\nMachine: {machine.line()}\n"]
    for name, title in SECTIONS:
        md = out_dir / f"{name}.md"
        if name in results and md.exists():
            parts.append(f"## {title}\n\n{md.read_text()}")
    plot = _plot(out_dir, results)
    if plot is not None:
        parts.append(f"![benchmarks]({plot.name})\n")
    summary = out_dir / "summary.md"
    summary.write_text("\n".join(parts))
    print(f"\nbodynet bench: {summary}" + (f", {plot}" if plot else ""))
    return summary
