"""PNG figures of the experiments, in the manner of seed 001's (Table XI bars, Fig. 12 traces, Fig. 13 sweep)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def _plt():  # noqa: ANN202
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def startup_bars(result: dict[str, Any], path: Path) -> Path:
    plt = _plt()
    names = list(result["joints"])
    w0 = [result["joints"][n]["starting_torque_without_Nm"] for n in names]
    w1 = [result["joints"][n]["starting_torque_with_Nm"] for n in names]
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(7, 3.6))
    ax.bar(x - 0.2, w0, 0.4, label="without start-up compensation")
    ax.bar(x + 0.2, w1, 0.4, label="with start-up compensation")
    for i, n in enumerate(names):
        ax.text(x[i] + 0.2, w1[i], f"−{result['joints'][n]['reduction_pct']:.0f} %", ha="center", va="bottom",
                fontsize=8)
    ax.set_xticks(x, names)
    ax.set_ylabel("starting torque [N·m]")
    ax.set_title(f"Start-up torque (mean reduction {result['mean_reduction_pct']:.1f} %)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def ramp_trace(rows: dict[str, np.ndarray], joint: int, path: Path, title: str) -> Path:
    plt = _plt()
    t = np.asarray(rows["t_s"], dtype=float)
    t = t - t[0]
    fig, axes = plt.subplots(3, 1, figsize=(7, 6), sharex=True)
    axes[0].plot(t, np.degrees(np.asarray(rows["q_rad"], dtype=float)[:, joint]))
    axes[0].set_ylabel("angle [°]")
    axes[1].plot(t, np.degrees(np.asarray(rows["dq_rad_s"], dtype=float)[:, joint]))
    axes[1].set_ylabel("velocity [°/s]")
    axes[2].plot(t, np.asarray(rows["current_command_A"], dtype=float)[:, joint], label="command", lw=0.8)
    axes[2].plot(t, np.asarray(rows["current_measured_A"], dtype=float)[:, joint], label="measured", lw=0.5, alpha=0.6)
    axes[2].set_ylabel("current [A]")
    axes[2].set_xlabel("time [s]")
    axes[2].legend(fontsize=8)
    axes[0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def sweep_plot(result: dict[str, Any], path: Path) -> Path:
    plt = _plt()
    f = [p["frequency_Hz"] for p in result["points"]]
    osc = [p["oscillation_deg"] for p in result["points"]]
    tq = [p["starting_torque_Nm"] for p in result["points"]]
    fig, ax = plt.subplots(figsize=(7, 3.6))
    ax.plot(f, tq, "o-", color="C0", label="starting torque")
    ax.set_xlabel("start-up compensation frequency [Hz]")
    ax.set_ylabel("starting torque [N·m]", color="C0")
    ax2 = ax.twinx()
    ax2.plot(f, osc, "s--", color="C1", label="oscillation range")
    ax2.axhline(result["oscillation_limit_deg"], color="C1", lw=0.8, ls=":")
    ax2.set_ylabel("oscillation range [°]", color="C1")
    best = result.get("best_frequency_Hz")
    if best is not None:
        ax.axvline(best, color="k", lw=0.8, ls=":")
    ax.set_title(f"{result['joint']}: start-up frequency sweep (chosen {best} Hz)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def quality_bars(result: dict[str, Any], path: Path) -> Path:
    plt = _plt()
    names = list(result["joints"])
    pct = [result["joints"][n]["effort_pct"] for n in names]
    fig, ax = plt.subplots(figsize=(7, 3.4))
    ax.bar(names, pct)
    ax.axhline(10.0, color="k", lw=0.8, ls=":")
    ax.set_ylabel("effort at 10°/s [% of uncompensated]")
    ax.set_title("Drag effort")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
