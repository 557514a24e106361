"""Sphinx extension: the documentation's figures, drawn at build time from real runs on ``sim://``.

A page asks for a figure by name::

    ```{sim-figure} sidbe-fit
    :alt: measured and simulated velocity
    The caption, in Markdown.
    ```

The first page that names a figure makes it: the run behind it goes through the
public API (``sb.sidbe``, ``sb.diagnose``, ``sb.validate``) on the simulated
drive, lock-step and seeded, so every build draws the same figures from the code
it documents. Runs are shared between figures and made once per build, in a
temporary folder; the PNG files go to ``<doctreedir>/sim-figures/`` (inside the
build's output folder), so a build writes nothing into the source tree.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from docutils import nodes
from docutils.parsers.rst import directives
from sphinx.application import Sphinx
from sphinx.util import logging
from sphinx.util.docutils import SphinxDirective

LOG = logging.getLogger(__name__)

#: The runs behind the figures: name -> (drive URL, sidbe keyword arguments).
RUNS: dict[str, tuple[str, dict[str, Any]]] = {
    # open loop, velocity noise 1 % of the amplitude: the tutorial's run
    "open": ("sim://?noise=0.01&seed=1", {"periods": 2, "period_s": 2.0}),
    # limited travel, +-0.05 rad: closed-loop excitation
    "closed": ("sim://?xmin=-0.05&xmax=0.05&noise=0.01&seed=2", {"periods": 2, "period_s": 2.0, "plots": False}),
    # a hidden Stribeck curve for diagnose to find
    "stribeck": ("sim://?stribeck_fs=0.8&stribeck_vs=0.05&noise=0.005&seed=3",
                 {"periods": 2, "period_s": 2.0, "plots": False}),
}  # fmt: skip


class _Runs:
    """The runs of one build, made on first use, in a folder removed when the build ends."""

    def __init__(self) -> None:
        self.tmp = Path(tempfile.mkdtemp(prefix="servobench-docs-"))
        self.done: dict[str, Any] = {}

    def sidbe(self, name: str) -> Any:
        if name not in self.done:
            import servobench as sb

            url, kwargs = RUNS[name]
            self.done[name] = sb.sidbe(url, out=self.tmp / name, **kwargs)
        return self.done[name]

    def diagnosis(self) -> Any:
        if "diagnose" not in self.done:
            import servobench as sb

            self.done["diagnose"] = sb.diagnose(
                self.sidbe("stribeck").log, out=self.tmp / "diagnose"
            )
        return self.done["diagnose"]

    def validation(self) -> Any:
        if "validate" not in self.done:
            import servobench as sb

            model = self.sidbe("open").model
            self.done["validate"] = sb.validate(
                model, self.sidbe("closed").log, out=self.tmp / "validate"
            )
        return self.done["validate"]

    def close(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)


# ---------------------------------------------------------------------------- the figures
def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def fig_sidbe_fit(runs: _Runs, png: Path) -> None:
    """Run 1 of the open-loop SIDBE run: measured velocity against the identified model's."""
    import servobench as sb

    plt = _pyplot()
    result = runs.sidbe("open")
    log = sb.read_log(result.log)
    run = log.runs[0]
    v_sim = result.model.simulate(run.u, fs=log.fs_hz, v0=float(run.v[0]))
    window = (run.t >= 2.0) & (run.t < 3.0)  # the second period: the first is the transient
    fig, (ax_v, ax_u) = plt.subplots(2, 1, sharex=True, figsize=(7.5, 4.2), height_ratios=(3, 1))
    ax_v.plot(
        run.t[window],
        run.v[window],
        ".",
        ms=2.5,
        color="0.55",
        label="measured v (sim://, noise 0.01)",
    )
    ax_v.plot(run.t[window], v_sim[window], lw=1.2, color="C0",
              label=f"simulated, identified model (fit {result.fit_percent:.1f} %)")  # fmt: skip
    ax_v.set_ylabel("v [rad/s]")
    ax_v.legend(loc="upper right", fontsize=8)
    ax_u.step(run.t[window], run.u[window], where="post", lw=0.8, color="C3")
    ax_u.set_ylabel("u [N m]")
    ax_u.set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def fig_closed_loop(runs: _Runs, png: Path) -> None:
    """Run 1 of the closed-loop SIDBE run: the position inside its travel window, and the commands."""
    import servobench as sb

    plt = _pyplot()
    result = runs.sidbe("closed")
    log = sb.read_log(result.log)
    run = log.runs[0]
    fig, (ax_x, ax_u) = plt.subplots(2, 1, figsize=(7.5, 4.6))
    ax_x.plot(run.t, run.x, lw=0.8, color="C0", label="x")
    if run.x_ref is not None:
        ax_x.plot(run.t, run.x_ref, lw=1.0, color="C2", label="x_ref (hold loop)")
    for limit in (-0.05, 0.05):
        ax_x.axhline(limit, color="C3", lw=1.0, ls="--")
    ax_x.set_ylabel("x [rad]")
    ax_x.set_xlabel("t [s]")
    ax_x.legend(loc="upper right", fontsize=8)
    ax_x.set_title("position, run 1; xmin/xmax = -0.05/0.05 rad (dashed)", fontsize=9)
    zoom = (run.t >= 1.0) & (run.t < 1.25)
    if run.u_exc is not None:
        ax_u.step(
            run.t[zoom],
            run.u_exc[zoom],
            where="post",
            lw=1.0,
            color="0.5",
            label="u_exc (excitation)",
        )
    ax_u.step(
        run.t[zoom],
        run.u[zoom],
        where="post",
        lw=0.9,
        color="C3",
        label="u (total command applied)",
    )
    ax_u.set_ylabel("u [N m]")
    ax_u.set_xlabel("t [s]")
    ax_u.set_title("commands, 1.00-1.25 s", fontsize=9)
    ax_u.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def _copy(path: Path, png: Path) -> None:
    shutil.copyfile(path, png)


def _plot_of(result: Any, name: str) -> Path:
    for path in result.plots:
        if Path(path).name == name:
            return Path(path)
    raise FileNotFoundError(f"the run wrote no {name}: {[Path(p).name for p in result.plots]}")


def _validation_png(runs: _Runs) -> Path:
    runs.validation()
    return runs.tmp / "validate" / "validation.png"


FIGURES: dict[str, Callable[[_Runs, Path], None]] = {
    "sidbe-fit": fig_sidbe_fit,
    "sidbe-frf": lambda runs, png: _copy(_plot_of(runs.sidbe("open"), "frf.png"), png),
    "sidbe-friction": lambda runs, png: _copy(_plot_of(runs.sidbe("open"), "friction.png"), png),
    "closed-loop": fig_closed_loop,
    "diagnose-residual": lambda runs, png: _copy(
        runs.diagnosis().report.parent / "residual_vs_state.png", png
    ),
    "diagnose-gaps": lambda runs, png: _copy(runs.diagnosis().report.parent / "gap_steps.png", png),
    "validation": lambda runs, png: _copy(_validation_png(runs), png),
}


# ---------------------------------------------------------------------------- Sphinx
def _runs(app: Sphinx) -> _Runs:
    runs = getattr(app, "_servobench_runs", None)
    if runs is None:
        runs = _Runs()
        app._servobench_runs = runs  # type: ignore[attr-defined]
    return runs


def figure_file(app: Sphinx, name: str) -> Path:
    """The PNG of figure ``name``, drawn in this build on first use."""
    folder = Path(app.doctreedir) / "sim-figures"
    png = folder / f"{name}.png"
    made: set[str] = getattr(app, "_servobench_figures", set())
    if name not in made:
        folder.mkdir(parents=True, exist_ok=True)
        partial = png.with_suffix(".part.png")
        FIGURES[name](_runs(app), partial)
        os.replace(partial, png)
        made.add(name)
        app._servobench_figures = made  # type: ignore[attr-defined]
    return png


class SimFigure(SphinxDirective):
    """``sim-figure NAME``: a figure drawn from a run on ``sim://``; the content is its caption."""

    required_arguments = 1
    has_content = True
    option_spec = {
        "alt": directives.unchanged,
        "width": directives.length_or_percentage_or_unitless,
    }

    def run(self) -> list[nodes.Node]:
        name = self.arguments[0]
        if name not in FIGURES:
            raise self.error(f"unknown sim-figure {name!r}; known: {', '.join(FIGURES)}")
        png = figure_file(self.env.app, name)
        here = Path(self.env.doc2path(self.env.docname)).parent
        image = nodes.image(
            uri=Path(os.path.relpath(png, here)).as_posix(), alt=self.options.get("alt", name)
        )
        if "width" in self.options:
            image["width"] = self.options["width"]
        figure = nodes.figure("", image, classes=["sim-figure"])
        if self.content:
            body = nodes.Element()
            self.state.nested_parse(self.content, self.content_offset, body)
            first = body.children[0] if body.children else None
            if isinstance(first, nodes.paragraph):
                figure += nodes.caption(first.rawsource, "", *first.children)
                if len(body.children) > 1:
                    figure += nodes.legend("", *body.children[1:])
            else:
                figure += nodes.legend("", *body.children)
        self.set_source_info(figure)
        return [figure]


def _cleanup(app: Sphinx, exception: BaseException | None) -> None:
    runs = getattr(app, "_servobench_runs", None)
    if runs is not None:
        runs.close()


def setup(app: Sphinx) -> dict[str, Any]:
    app.add_directive("sim-figure", SimFigure)
    app.connect("build-finished", _cleanup)
    return {"version": "1", "parallel_read_safe": False, "parallel_write_safe": True}
