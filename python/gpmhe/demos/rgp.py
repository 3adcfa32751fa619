"""RGP-dKF demo: ``python -m gpmhe demo rgp [options]``.

The RGP-dKF learning the hidden disturbance of the second-order system (scenario S2: low noise,
both states measured), as in the paper's Figs. 1-2. Prints the RMSE and NLL of the learned z(ζ)
over the visited ζ range after 0.5 s and after the whole run, and writes a figure of the GP mean
±2σ against the truth at both times (needs matplotlib).
"""

from __future__ import annotations

import argparse
from typing import Any, Sequence

import numpy as np

from gpmhe.rgp import RecursiveGP
from gpmhe.systems import second_order as so


def gp_from_weights(mean: np.ndarray, cov: np.ndarray) -> RecursiveGP:
    """A RecursiveGP of the example's grid carrying the given weights (for evaluating snapshots)."""
    gp = so.make_gp()
    gp.set_weights(mean, cov)
    return gp


def plot_learned(ax: Any, gp: RecursiveGP, run: so.Run, title: str) -> None:
    """GP mean ±2σ against the true z(ζ) on one matplotlib axis, with the visited ζ range marked."""
    g = np.linspace(so.ZETA_BOUNDS[0], so.ZETA_BOUNDS[1], 300)
    m, s = gp.predict(g, return_std=True)
    ax.fill_between(g, m - 2 * s, m + 2 * s, color="C0", alpha=0.25, label="GP ±2σ")
    ax.plot(g, m, color="C0", label="GP mean")
    ax.plot(g, so.disturbance(g), "k--", label="true z(ζ)")
    lo, hi = np.quantile(run.zeta, [0.01, 0.99])
    ax.axvspan(lo, hi, color="0.9", zorder=0, label="visited ζ (1–99 %)")
    ax.set_ylim(-110, 90)
    ax.set_xlabel("ζ")
    ax.set_ylabel("z")
    ax.set_title(title)
    ax.legend(loc="lower left", fontsize=8)


def write_figure(path: str, panels: Sequence[tuple[RecursiveGP, so.Run, str]]) -> bool:
    """One panel per (gp, run, title); returns False (with a message) if matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no figure written (pip install matplotlib)")
        return False
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), squeeze=False)
    for ax, (gp, run, title) in zip(axes[0], panels):
        plot_learned(ax, gp, run, title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    print(f"figure written to {path}")
    return True


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gpmhe demo rgp",
                                     description=__doc__.split("\n", 2)[2].strip())
    parser.add_argument("--out", default="rgp_s2.png", help="figure path (default: rgp_s2.png)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=so.DURATION, help="seconds of data")
    args = parser.parse_args(list(argv) if argv is not None else None)
    if not args.duration > 0.5:
        parser.error("--duration must exceed 0.5 s")

    noise, output = so.SCENARIOS["S2"]
    run = so.simulate(args.seed, noise, output, duration=args.duration)
    early = int(round(0.5 / so.T))
    ekf, snaps, xs = so.run_rgp_dkf(run, snapshots=(early,))
    g = so.evaluation_grid(run)
    truth = so.disturbance(g)
    gp_early = gp_from_weights(*snaps[early])
    gp_late = gp_from_weights(*ekf.gp_weights())
    print(f"RGP-dKF, scenario S2 (noise std {so.NOISE[noise]}, y = x), seed {args.seed}, "
          f"T = {so.T} s, {len(run.u)} steps")
    for label, gp in ((f"after {early * so.T:.1f} s", gp_early),
                      (f"after {len(run.u) * so.T:.1f} s", gp_late)):
        m, s = gp.predict(g, return_std=True)
        rmse, nll = so.rmse_nll(m, s, truth)
        print(f"  {label:>14}: RMSE of z over visited ζ = {rmse:.3f}, NLL = {nll:.3f}")
    err = np.sqrt(np.mean((xs - run.x) ** 2, axis=0))
    print(f"  state RMSE: x1 {err[0]:.4f}, x2 {err[1]:.4f}")
    write_figure(args.out, [(gp_early, run, f"S2: {early * so.T:.1f} s of training"),
                            (gp_late, run, f"S2: {len(run.u) * so.T:.0f} s of training")])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
