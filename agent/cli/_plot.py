"""MSE-against-step figures (matplotlib, Agg backend), in the style of the paper's figures."""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: what matplotlib's Agg backend writes, by file suffix
FIGURE_SUFFIXES = (".png", ".pdf", ".svg", ".svgz", ".ps", ".eps", ".jpg", ".jpeg", ".tif",
                   ".tiff", ".webp", ".pgf")


def figure_path(text: str, flag: str = "--plot") -> Path:
    """The figure file a ``--plot`` value names, checked before any work is done: no
    suffix -> ``.png``; a suffix matplotlib cannot write, or a folder that does not
    exist, is an error naming the flag.

    >>> figure_path("mse"), figure_path("fig.pdf")
    (PosixPath('mse.png'), PosixPath('fig.pdf'))
    """
    from agent.cli._common import CommandError

    path = Path(text)
    if not path.suffix:
        path = path.with_name(path.name + ".png")
    if path.suffix.lower() not in FIGURE_SUFFIXES:
        raise CommandError(f"{flag}: cannot write a {path.suffix!r} figure; use one of "
                           f"{', '.join(FIGURE_SUFFIXES)}")
    if not path.parent.is_dir():
        raise CommandError(f"{flag}: folder {str(path.parent)!r} does not exist")
    return path


#: the curves' line styles, in order (solid, dashed, dash-dot, dotted, dash-dot-dot)
STYLES = ("-", "--", "-.", ":", (0, (5, 2, 1, 2, 1, 2)))


def plot_mse(path, curves, title=None, events=(), band=(10.0, 90.0), reference=()) -> None:
    """Write a log-scale MSE figure to ``path``.

    Parameters
    ----------
    curves : list of (label, SimulationResult)
        One line (mean over trials) and one shaded band (percentiles ``band`` across
        trials) per result.
    events : list of (step, label)
        Vertical dashed lines (failure, recovery).
    reference : list of (value, label) or (value, label, first step, last step)
        Horizontal dotted lines (e.g. the exact steady MSE), over the steps given.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.0, 3.8), dpi=150)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for idx, (label, res) in enumerate(curves):
        c = colors[idx % len(colors)]
        k = np.arange(res.mse.size)
        lo, hi = res.band(*band)
        finite = np.isfinite(res.mse) & (res.mse > 0)
        ax.fill_between(k[finite], lo[finite], hi[finite], color=c, alpha=0.2, linewidth=0)
        # a line style each: curves that coincide (the same run before a failure) all show
        ax.plot(k[finite], res.mse[finite], color=c, linewidth=1.2, label=label,
                linestyle=STYLES[idx % len(STYLES)])
    for idx, (value, label, *span) in enumerate(reference):
        if value is not None and np.isfinite(value) and value > 0:
            style = dict(color=colors[idx % len(colors)], linestyle=":", linewidth=1.0,
                         label=label)
            if span:                     # the steps over which the level holds
                ax.hlines(value, *span, **style)
            else:
                ax.axhline(value, **style)
    for step, label in events:
        ax.axvline(step, color="k", linestyle="--", linewidth=0.9)
        ax.annotate(label, xy=(step, 0.0), xycoords=("data", "axes fraction"),
                    xytext=(3, 4), textcoords="offset points", fontsize=7)
    ax.set_yscale("log")
    ax.set_xlabel("time step k")
    ax.set_ylabel("mean-squared estimation error")
    if title:
        ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="best", framealpha=0.8)
    if curves:
        ax.set_xlim(0, max(res.steps for _, res in curves))
    band_note = f"mean over trials; band: {band[0]:g}-{band[1]:g} percentile across trials"
    fig.text(0.01, 0.005, band_note, fontsize=6, color="0.4")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
