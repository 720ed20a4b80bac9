"""The figures the docs quote, rendered from the results files of the bench commands.

Each bench command writes ``results.json`` into its ``--out`` folder; a copy of it, without the
per-object records, is ``docs/results/<source>/results.json`` (:data:`SOURCES` names every
source and the command that writes it; ``examples/docs_figures.sh`` runs them all and copies
their files with :func:`collect`). A table the docs show from those files stands between two
markers::

    <!-- figures: table1-paper-structure -->

    | method | accuracy | ... |

    <!-- /figures -->

:func:`check` renders every marked block from its sources (:data:`FIGURES`) and names each block
whose text differs; :func:`write` puts the rendered text in place. Numbers quoted in sentences
are checked as sentences (:data:`QUOTES`: each rendered sentence must be in the file). A figure
whose sources are not all in ``docs/results`` yet is *incomplete*: its rows from the sources
present are checked (bold ignored), the rest waits for ``examples/docs_figures.sh``;
``ssp bench docs-figures --check --strict`` counts it as a failure.

The tower case study's single-seed tables and the parser's side-by-side timing table are
rendered by the bench's own writers (:func:`ssp.eval.tower.write_tower`,
:func:`ssp.eval.bench_parser.write_compare`, into a temporary folder); the other tables lay
several runs out side by side, which no bench report does, so their rows are written here with
the bench's cell format (:func:`ssp.eval.metrics.plus_minus`).
"""

from __future__ import annotations

import json
import logging
import re
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ssp.errors import SSPError
from ssp.eval.metrics import plus_minus
from ssp.io._files import atomic_write_text

__all__ = [
    "FIGURES",
    "QUOTES",
    "SOURCES",
    "Figure",
    "Problem",
    "Quote",
    "Source",
    "check",
    "collect",
    "write",
]

log = logging.getLogger(__name__)

RESULTS = Path("docs/results")
BEGIN = re.compile(r"^<!-- figures: ([\w.-]+) -->$")
END = "<!-- /figures -->"
SEEDS = (1000, 2000, 3000)
BASELINES = "estimator,icp,ray_slide,bestfit,temporal_filter,icp_filter"
LINKS = "../shared/data/costar-links"
LMO = "../shared/data/lmo-megapose"
PARSER_REV = "3d6b73d"
REAL_DEV = "../shared/data/real-dev"
#: The revision before issue 34's speed-ups, timed beside this code by ``ssp bench frame``.
FRAME_REV = "c436e9b"
#: The code before the ICPs in threads and the compiled self-occlusion test (frame-threads).
THREADS_REV = "ef47c46"
#: The code before the segments in threads and the compiled lookups (frame-kernels).
KERNELS_REV = "3b8973d"


@dataclass(frozen=True)
class Source:
    """One bench run: ``command`` (without ``--out``) writes ``file`` into its folder, copied
    to ``docs/results/<name>/<file>``."""

    name: str
    command: str
    file: str = "results.json"


#: The mug protocol's model folder (``ssp models export-builtin MUG_MODELS --names ...``,
#: examples/docs_figures.sh).
MUG_MODELS = "bench-out/mug-models"


def _sources() -> dict[str, Source]:
    out: list[Source] = []
    for e in ("isolated", "structure"):
        base = f"ssp bench table1 --experiment {e} --sequences 10 --seed 1000"
        out += [
            Source(f"t1-{e}-paper-ssp", f"{base} --methods ssp,ssp_single"),
            Source(f"t1-{e}-paper-baselines", f"{base} --methods {BASELINES}"),
            Source(f"t1-{e}-realistic-ssp", f"{base} --noise realistic --methods ssp"),
            Source(f"t1-{e}-realistic-baselines",
                   f"{base} --noise realistic --methods {BASELINES}"),
            Source(f"t1-{e}-realistic-single", f"{base} --noise realistic --methods ssp_single"),
            Source(f"t1-{e}-estimated",
                   f"{base} --hypotheses estimated --methods ssp,estimator,icp,icp_filter"),
            Source(f"t1-{e}-rgb", f"{base} --noise rgb"),
            Source(f"t1-{e}-nomask", f"{base} --noise realistic --masks none --methods "
                                     "ssp,ssp_single,estimator,icp_filter"),
        ]  # fmt: skip
    mug = ("ssp bench table1 --experiment isolated --sequences 10 --seed 1000 --models "
           f"{MUG_MODELS}")  # fmt: skip
    out += [
        Source("t1-isolated-mug",
               f"{mug} --hypotheses estimated --methods ssp,ssp_single,estimator,icp_filter"),
        Source("t1-isolated-mug-realistic",
               f"{mug} --noise realistic --methods ssp,ssp_single,estimator,icp_filter"),
        Source("t1-isolated-mug-nomask", f"{mug} --hypotheses estimated --masks none "
                                         "--methods ssp,ssp_single,estimator,icp_filter"),
    ]  # fmt: skip
    moving = ("ssp bench table1 --experiment structure --sequences 10 --seed 1000 --noise "
              "realistic --methods ssp,icp_filter --camera")  # fmt: skip
    tools = moving.replace("--experiment structure", "--experiment isolated")
    located = "--camera-pose estimated"
    out += [
        Source("t1-structure-realistic-orbit", f"{moving} orbit"),
        Source("t1-structure-realistic-keyframes", f"{moving} keyframes"),
        Source("t1-structure-realistic-orbit-located", f"{moving} orbit {located}"),
        Source("t1-structure-realistic-keyframes-located", f"{moving} keyframes {located}"),
        Source("t1-isolated-realistic-orbit", f"{tools} orbit"),
        Source("t1-isolated-realistic-orbit-located", f"{tools} orbit {located}"),
        Source("camera-bench", "ssp bench camera --sequences 2 --seed 1000"),
        Source("camera-bench-2000", "ssp bench camera --sequences 3 --seed 2000"),
    ]
    tower = "ssp bench tower --trials 10"
    for s in SEEDS:
        real = f"{tower} --seed {s} --noise realistic --methods"
        out += [
            Source(f"tower-realistic-ssp-{s}", f"{real} ssp"),
            Source(f"tower-realistic-single-{s}", f"{real} ssp_single"),
            Source(f"tower-realistic-base-{s}", f"{real} {BASELINES}"),
            Source(f"tower-structure-ssp-{s}", f"{tower} --seed {s} --methods ssp"),
            Source(f"tower-structure-estimator-{s}", f"{tower} --seed {s} --methods estimator"),
        ]
    for s in SEEDS:
        out.append(
            Source(
                f"tower-wrist-ssp-{s}",
                f"{tower} --seed {s} --noise realistic --methods ssp --camera wrist",
            )
        )
    out.append(Source("tower-wrist-base-1000", f"{tower} --seed 1000 --noise realistic --methods "
                      "estimator,icp_filter,ray_slide --camera wrist"))  # fmt: skip
    est = f"{tower} --seed 1000 --hypotheses estimated --methods"
    out += [
        Source("tower-case-study", f"{tower} --seed 1000 --noise case-study"),
        Source("tower-rgb", f"{tower} --seed 1000 --noise rgb"),
        Source("rgb-calibration", f"ssp bench rgb-calibration --data {LMO}"),
        Source("tower-estimated-ssp", f"{est} ssp"),
        Source("tower-estimated-estimator", f"{est} estimator"),
        Source("parser-compare",
               f"ssp bench parser --links {LINKS} --compare {PARSER_REV} --processes 2 "
               "--rev-processes 2", "compare.json"),
        Source("frame-compare",
               f"ssp bench frame --real-dev {REAL_DEV} --compare {FRAME_REV} --rounds 2"),
        Source("frame-processes", "ssp bench frame --processes 2"),
        Source("frame-threads",
               f"ssp bench frame --real-dev {REAL_DEV} --compare {THREADS_REV} --rounds 1"),
        Source("frame-kernels",
               f"ssp bench frame --real-dev {REAL_DEV} --compare {KERNELS_REV} --rounds 1"),
    ]  # fmt: skip
    return {s.name: s for s in out}


#: Every bench run the docs quote, by name.
SOURCES = _sources()

Results = dict[str, dict]  # source name -> its results (the sources present)


@dataclass(frozen=True)
class Figure:
    """A marked block: ``render(results)`` gives its lines from the sources present (every
    row it can: a row needs its own sources only)."""

    name: str
    sources: tuple[str, ...]
    render: Callable[[Results], list[str]]


@dataclass(frozen=True)
class Quote:
    """Sentences of ``file`` that quote figures: each string ``render(results)`` gives must be
    in the file (whitespace runs read as one space)."""

    name: str
    file: str
    sources: tuple[str, ...]
    render: Callable[[Results], list[str]]


@dataclass
class Problem:
    """What :func:`check` found: ``kind`` is ``differs``, ``incomplete`` or ``unknown``."""

    kind: str
    where: str
    message: str
    missing: list[str] = field(default_factory=list)

    def __str__(self) -> str:
        return f"{self.where}: {self.message}"


# ------------------------------------------------------------------------------ cells
def _pen(v: float) -> str:
    """A penetration depth, mm, to about three digits (0.18, 25.6, 264)."""
    return f"{v:.2f}" if v < 10 else f"{v:.1f}" if v < 100 else f"{v:.0f}"


def _switches(d: dict) -> str:
    sw = d.get("id_switches")
    return "-" if sw is None else f"{sw} ({d['id_switches_static']})"


def _number(cell: str) -> float | None:
    m = re.match(r"\s*(-?[\d.]+)", cell)
    return float(m.group(1)) if m else None


def _bold_best(rows: list[list[str]], columns: dict[int, bool]) -> None:
    """Bold, in place, the best value of each column in ``columns`` (index -> higher is
    better), each `` / ``-separated part on its own; ties are all bold, and a column where
    every row ties is left plain. Cells without a number (``-``, empty) take no part."""
    for c, higher in columns.items():
        parts = [r[c].split(" / ") if r[c] else [] for r in rows]
        for p in range(max((len(x) for x in parts), default=0)):
            vals = [_number(x[p]) if p < len(x) else None for x in parts]
            known = [v for v in vals if v is not None]
            if len(set(known)) < 2:
                continue
            best = max(known) if higher else min(known)
            for x, v in zip(parts, vals, strict=True):
                if v == best:
                    x[p] = f"**{x[p]}**"
        for r, x in zip(rows, parts, strict=True):
            if x:
                r[c] = " / ".join(x)


def _table(header: Sequence[str], rows: list[list[str]]) -> list[str]:
    """Markdown lines of a table (an empty cell is ``| |``)."""

    def line(cells: Sequence[str]) -> str:
        return "|" + "|".join(f" {c} " if c else " " for c in cells) + "|"

    return [line(header), "|" + "---|" * len(header), *(line(r) for r in rows)]


def _methods(results: Results, sources: Sequence[str]) -> dict[str, dict]:
    """The methods of the sources present, in source order (a method in two: the first)."""
    out: dict[str, dict] = {}
    for s in sources:
        for name, d in results.get(s, {}).get("methods", {}).items():
            out.setdefault(name, d)
    return out


def _name(method: str) -> str:
    return f"**{method}**" if method == "ssp" else method


# ------------------------------------------------------------------------------ Table I
def _realistic(e: str) -> tuple[str, ...]:
    return (f"t1-{e}-realistic-ssp", f"t1-{e}-realistic-baselines", f"t1-{e}-realistic-single")


def _realistic_table(e: str, sources: tuple[str, ...] | None = None):
    """The stream table of experiment ``e`` from ``sources`` (default: the realistic
    stream's runs)."""
    sources = _realistic(e) if sources is None else sources

    def render(results: Results) -> list[str]:
        rows = []
        for name, d in _methods(results, sources).items():
            b, a = d["bop"], d["accuracy"]
            rows.append([
                _name(name), f"{b['AR']:.3f}",
                f"{b['AR_VSD']:.3f} / {b['AR_MSSD']:.3f} / {b['AR_MSPD']:.3f}",
                f"{d['gross_rate']:.3f}", f"{d['gross_rate_visible']:.3f}",
                f"{d['missed_per_frame']:.2f}", f"{d['false_positives_per_frame']:.2f}",
                _switches(d), f"{a['trans_mm_mean']:.2f} / {a['rot_deg_mean']:.2f}",
                _pen(d["max_penetration_mm"]),
            ])  # fmt: skip
        _bold_best(rows, {1: True, 3: False, 4: False, 5: False, 6: False, 7: False, 9: False})
        header = ("method", "AR", "VSD / MSSD / MSPD", "gross", "gross, visible",
                  "missed / frame", "false objects / frame", "id switches (static)",
                  "accuracy mm / deg", "max penetration mm")  # fmt: skip
        return _table(header, rows)

    return render


def _per_class_figure(source: str) -> Callable[[Results], list[str]]:
    """The per-class table of a Table I run (``ssp.eval.table1``'s, without its title)."""

    def render(results: Results) -> list[str]:
        from ssp.eval.table1 import per_class_markdown

        lines = per_class_markdown(results[source]["methods"])
        return lines[3:]

    return render


CONDITIONS = {
    "dropout": "dropout", "hidden": "hidden", "never_detected": "never detected",
    "nominal": "nominal", "top1_confusion": "best-scored confused",
    "top1_flip": "best-scored flipped", "top1_gross": "best-scored gross",
}  # fmt: skip


def _conditions_table(e: str) -> Callable[[Results], list[str]]:
    def render(results: Results) -> list[str]:
        methods = _methods(results, _realistic(e))
        keys = [
            k for k in CONDITIONS if any(k in d["gross_by_condition"] for d in methods.values())
        ]
        rows = []
        for name, d in methods.items():
            g = d["gross_by_condition"]
            rows.append([_name(name)] + [
                f"{g[k]['gross']} / {g[k]['object_frames']}" if k in g else "" for k in keys
            ])  # fmt: skip
        _bold_best(rows, dict.fromkeys(range(1, len(keys) + 1), False))
        return _table([e, *(CONDITIONS[k] for k in keys)], rows)

    return render


def _ranked(methods: dict[str, dict], key: Callable[[dict], float], higher: bool):
    others = sorted(
        ((key(d), n) for n, d in methods.items() if n != "ssp"), key=lambda t: t[0], reverse=higher
    )
    return key(methods["ssp"]), others


def _acceptance(results: Results) -> list[str]:
    cells: dict[str, list[str]] = {"ar": [], "gross": [], "switches": []}
    for e in ("structure", "isolated"):
        methods = _methods(results, _realistic(e))
        if "ssp" not in methods or len(methods) < 3:
            return []
        ar, others = _ranked(methods, lambda d: d["bop"]["AR"], higher=True)
        nxt = ", ".join(f"`{n}` {v:.3f}" for v, n in others[:2])
        cells["ar"].append(f"{ar:.3f} (next: {nxt})")
        g, others = _ranked(methods, lambda d: d["gross_rate"], higher=False)
        (bv, bn) = others[0]
        cells["gross"].append(f"{g:.3f} = {g / bv:.2f} x `{bn}`'s {bv:.3f}")
        d = methods["ssp"]
        cells["switches"].append(
            f"{d['id_switches_static']} ({d['id_switches'] - d['id_switches_static']} of "
            "moved objects)"
        )
    return _table(
        ("target", "structure", "isolated"),
        [
            ["ssp has the best AR", *cells["ar"]],
            ["ssp's gross rate at most a quarter of the best baseline's", *cells["gross"]],
            ["zero id switches of static objects", *cells["switches"]],
        ],
    )


def _paper(e: str) -> tuple[str, ...]:
    return (f"t1-{e}-paper-ssp", f"t1-{e}-paper-baselines")


def _pm2(d: dict) -> str:
    return (
        f"{plus_minus(d['trans_mm_mean'], d['trans_mm_std'])} / "
        f"{plus_minus(d['rot_deg_mean'], d['rot_deg_std'])}"
    )


def _paper_table(e: str) -> Callable[[Results], list[str]]:
    from ssp.eval.table1 import PAPER_TABLE1

    def render(results: Results) -> list[str]:
        rows = []
        for name, d in _methods(results, _paper(e)).items():
            rows.append([
                _name(name), _pm2(d["accuracy"]), _pm2(d["precision"]),
                f"{d['bop']['AR']:.3f}", f"{d['gross_rate']:.3f}",
                f"{d['missed_per_frame']:.2f} / {d['false_positives_per_frame']:.2f}",
                _switches(d), _pen(d["max_penetration_mm"]),
                f"{d['unsupported_objects']:.2f}", f"{d['sec_per_frame']:#.2g}",
            ])  # fmt: skip
        _bold_best(rows, dict.fromkeys((1, 2, 5, 6, 7, 8), False) | {3: True, 4: False})
        blank = [""] * 8
        first = results.get(_paper(e)[0]) or results.get(_paper(e)[1])
        if first:
            rows.insert(0, ["hypotheses (induced noise)", _pm2(first["induced_noise"]), *blank])
        p = PAPER_TABLE1[e]
        paper = [f"{m} ± {s} / {rm} ± {rs}" for (m, s), (rm, rs) in (p["accuracy"], p["precision"])]
        rows.append(["paper (ssp on Gazebo)", *paper, *blank[1:]])
        header = ("method", "accuracy", "precision", "AR", "gross", "missed / false per frame",
                  "id switches (static)", "max penetration mm", "unsupported / frame",
                  "s / frame")  # fmt: skip
        return _table(header, rows)

    return render


# ------------------------------------------------------------------------------ tower
def _merged_tower(results: Results, sources: Sequence[str]) -> dict | None:
    """One tower result with the methods of every source (None unless all are present)."""
    if any(s not in results for s in sources):
        return None
    out = dict(results[sources[0]])
    out["methods"] = _methods(results, sources)
    out["trials_detail"] = {}
    for s in sources:
        out["trials_detail"].update(results[s]["trials_detail"])
    return out


def _tower_report_table(sources: tuple[str, ...]) -> Callable[[Results], list[str]]:
    """The first table of the ``results.md`` that :func:`ssp.eval.tower.write_tower` writes."""

    def render(results: Results) -> list[str]:
        from ssp.eval.tower import write_tower

        result = _merged_tower(results, sources)
        if result is None:
            return []
        with tempfile.TemporaryDirectory() as tmp:
            write_tower(result, tmp)
            text = (Path(tmp) / "results.md").read_text(encoding="utf-8")
        return _first_table(text)

    return render


def _first_table(markdown: str, skip: int = 0) -> list[str]:
    """The first Markdown table of ``markdown`` after ``skip`` others."""
    lines = markdown.splitlines()
    start = 0
    for _ in range(skip + 1):
        start = next(i for i in range(start, len(lines)) if lines[i].startswith("|"))
        end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")),
                   len(lines))  # fmt: skip
        table, start = lines[start:end], end
    return table


def _tower_cell(r: dict, trials: int, ghosts: bool) -> str:
    return (
        f"{plus_minus(r['stacks_mean'], r['stacks_std'])}, {r['full_towers']}/{trials}, "
        f"{r['ghost_cubes']}" + (" ghosts" if ghosts else "")
    )


TOWER_REALISTIC = ("ssp", "ssp_single", "estimator", "icp", "ray_slide", "bestfit",
                   "temporal_filter", "icp_filter")  # fmt: skip


def _tower_realistic(results: Results) -> list[str]:
    rows = []
    for i, s in enumerate(SEEDS):
        kinds = ("ssp", "single", "base")
        r = _merged_tower(results, [f"tower-realistic-{k}-{s}" for k in kinds])
        if r is None:
            continue
        m = r["methods"]
        rows.append([str(s), *(_tower_cell(m[k], r["trials"], i == 0) for k in TOWER_REALISTIC)])
    return _table(("seed", *TOWER_REALISTIC), rows)


def _failures(r: dict) -> str:
    f = r["failures"]
    return f" ({', '.join(f'{k}: {v}' for k, v in sorted(f.items()))})" if f else ""


def _tower_structure(results: Results) -> list[str]:
    runs = [_merged_tower(results, [f"tower-structure-{k}-{s}" for k in ("ssp", "estimator")])
            for s in SEEDS]  # fmt: skip
    if any(r is None for r in runs):
        return []
    cols: list[list[str]] = []
    for m in ("ssp", "estimator"):
        rs = [(r["methods"][m], r["trials"]) for r in runs if r is not None]
        cols.append([
            ", ".join(f"{d['full_towers']}/{n}{_failures(d)}" for d, n in rs),
            ", ".join(str(d["ghost_cubes"]) for d, _ in rs),
            ", ".join(f"{d['straightness_mm']:.2f} / {d['straightness_deg']:.2f}" for d, _ in rs),
            ", ".join(f"{d['consistency_mm']:.2f} / {d['consistency_deg']:.2f}" for d, _ in rs),
        ])  # fmt: skip
    labels = ("full towers", "ghost cubes", "straightness, mm / deg", "consistency, mm / deg")
    return _table(
        ("", "ssp", "estimator"), [[lab, *c] for lab, *c in zip(labels, *cols, strict=True)]
    )


# ------------------------------------------------------------------------------ frame
def _frame_table(source: str, skip: int) -> Callable[[Results], list[str]]:
    """The ``skip``-th table of ``ssp bench frame``'s results.md (0: the latency, side by side
    with the compared revision's when there is one; 1: issue 34's targets), from ``source``'s
    results.json."""

    def render(results: Results) -> list[str]:
        from ssp.eval.bench_frame import markdown_report

        if source not in results:
            return []
        return _first_table(markdown_report(results[source]), skip)

    return render


# ------------------------------------------------------------------------------ parser
def _parser_compare(results: Results) -> list[str]:
    from ssp.eval.bench_parser import write_compare

    if "parser-compare" not in results:
        return []
    with tempfile.TemporaryDirectory() as tmp:
        _, md = write_compare(results["parser-compare"], Path(tmp))
        return _first_table(md.read_text(encoding="utf-8"))


def _figures() -> dict[str, Figure]:
    out = [
        Figure("tower-realistic", tuple(f"tower-realistic-{k}-{s}" for s in SEEDS
                                        for k in ("ssp", "single", "base")), _tower_realistic),
        Figure("tower-structure", tuple(f"tower-structure-{k}-{s}" for s in SEEDS
                                        for k in ("ssp", "estimator")), _tower_structure),
        Figure("tower-case-study", ("tower-case-study",),
               _tower_report_table(("tower-case-study",))),
        Figure("tower-estimated", ("tower-estimated-ssp", "tower-estimated-estimator"),
               _tower_report_table(("tower-estimated-ssp", "tower-estimated-estimator"))),
        Figure("realistic-acceptance", _realistic("structure") + _realistic("isolated"),
               _acceptance),
        Figure("parser-compare", ("parser-compare",), _parser_compare),
        Figure("frame-compare", ("frame-compare",), _frame_table("frame-compare", 0)),
        Figure("frame-targets", ("frame-compare",), _frame_table("frame-compare", 1)),
        Figure("frame-processes", ("frame-processes",), _frame_table("frame-processes", 0)),
        Figure("frame-threads", ("frame-threads",), _frame_table("frame-threads", 0)),
        Figure("frame-kernels", ("frame-kernels",), _frame_table("frame-kernels", 0)),
        Figure("frame-kernels-targets", ("frame-kernels",), _frame_table("frame-kernels", 1)),
        Figure("tower-rgb", ("tower-rgb",), _tower_report_table(("tower-rgb",))),
    ]  # fmt: skip
    for name, src in (("mug-estimated", "t1-isolated-mug"),
                      ("mug-realistic", "t1-isolated-mug-realistic"),
                      ("mug-nomask", "t1-isolated-mug-nomask")):  # fmt: skip
        out += [
            Figure(name, (src,), _realistic_table("isolated", (src,))),
            Figure(f"{name}-classes", (src,), _per_class_figure(src)),
        ]
    for e in ("structure", "isolated"):
        out += [
            Figure(f"realistic-{e}", _realistic(e), _realistic_table(e)),
            Figure(f"realistic-conditions-{e}", _realistic(e), _conditions_table(e)),
            Figure(f"table1-paper-{e}", _paper(e), _paper_table(e)),
            Figure(f"rgb-{e}", (f"t1-{e}-rgb",), _realistic_table(e, (f"t1-{e}-rgb",))),
            Figure(f"nomask-{e}", (f"t1-{e}-nomask",), _realistic_table(e, (f"t1-{e}-nomask",))),
        ]
    return {f.name: f for f in out}


#: Every figure block the docs may mark, by name.
FIGURES = _figures()


# ------------------------------------------------------------------------------ sentences
def _readme_realistic(results: Results) -> list[str]:
    s = results["t1-structure-realistic-ssp"]["methods"]["ssp"]
    i = results["t1-isolated-realistic-ssp"]["methods"]["ssp"]
    tools = (
        "no false objects on tools"
        if i["false_positives_per_frame"] == 0
        else f"{i['false_positives_per_frame']:.2f} false objects per frame on tools"
    )
    return [
        f"ssp's BOP average recall is {s['bop']['AR']:.3f} on block structures and "
        f"{i['bop']['AR']:.3f} on tools, with {100 * s['gross_rate']:.1f} % and "
        f"{100 * i['gross_rate']:.1f} % of object-frames more than 1 cm or 10 deg off or "
        f"missing, {tools} ({s['false_positives_per_frame']:.2f} per frame on structures)",
    ]


def _readme_baselines(results: Results) -> list[str]:
    ms = _methods(results, _realistic("structure"))
    mi = _methods(results, _realistic("isolated"))
    f, g = ms["icp_filter"], mi["icp_filter"]
    fp = (f["false_positives_per_frame"] + g["false_positives_per_frame"]) / 2
    a, b = ms["ssp_single"], mi["ssp_single"]
    return [
        f"reaches {f['bop']['AR']:.2f} / {g['bop']['AR']:.2f} AR with "
        f"{100 * f['gross_rate']:.1f} % / {100 * g['gross_rate']:.1f} % gross errors and "
        f"{fp:.0f} false objects per frame; the parser without memory {a['bop']['AR']:.2f} / "
        f"{b['bop']['AR']:.2f} and {100 * a['gross_rate']:.0f} % / {100 * b['gross_rate']:.0f} %"
    ]


def _readme_paper(results: Results) -> list[str]:
    i = results["t1-isolated-paper-ssp"]["methods"]["ssp"]["accuracy"]
    s = results["t1-structure-paper-ssp"]["methods"]["ssp"]["accuracy"]
    return [
        f"ssp's poses are off by {i['trans_mm_mean']:.2f} mm / {i['rot_deg_mean']:.2f} deg "
        f"(tools) and {s['trans_mm_mean']:.2f} mm / {s['rot_deg_mean']:.2f} deg (structures)"
    ]


def _readme_estimated(results: Results) -> list[str]:
    i = results["t1-isolated-estimated"]["methods"]["ssp"]["accuracy"]
    s = results["t1-structure-estimated"]["methods"]["ssp"]["accuracy"]
    return [
        f"with hypotheses from the built-in perception front end {i['trans_mm_mean']:.2f} mm / "
        f"{i['rot_deg_mean']:.1f} deg and {s['trans_mm_mean']:.2f} mm / "
        f"{s['rot_deg_mean']:.2f} deg"
    ]


def _readme_tower(results: Results) -> list[str]:
    real = [_merged_tower(results, [f"tower-realistic-{k}-{s}" for k in ("ssp", "single", "base")])
            for s in SEEDS]  # fmt: skip
    struct = [_merged_tower(results, [f"tower-structure-{k}-{s}" for k in ("ssp", "estimator")])
              for s in SEEDS]  # fmt: skip
    rr = [r for r in real if r is not None]
    sr = [r for r in struct if r is not None]

    def full(rs: list[dict], m: str) -> int:
        return sum(r["methods"][m]["full_towers"] for r in rs)

    if not rr or not sr:
        return []
    n = sum(r["trials"] for r in rr)
    others = max(r["methods"][m]["full_towers"] for r in rr for m in TOWER_REALISTIC[2:])

    def span(m: str) -> str:
        v = [r["methods"][m]["straightness_mm"] for r in sr]
        return f"{min(v):.2f}-{max(v):.2f}"

    ns = sum(r["trials"] for r in sr)
    return [
        f"ssp built {full(rr, 'ssp')} towers of {n} on that stream (seeds "
        f"{', '.join(str(s) for s in SEEDS)}) where the parser without memory built "
        f"{full(rr, 'ssp_single')} and the other baselines at most {others} of "
        f"{rr[0]['trials']} per seed; with Table I's noise it built {full(sr, 'ssp')} of {ns} "
        f"with straightness {span('ssp')} mm per level (the estimator "
        f"{full(sr, 'estimator')} of {ns}, {span('estimator')} mm)"
    ]


def _rgb_calibration(results: Results) -> list[str]:
    r = results["rgb-calibration"]
    o = r["overall"]
    return [
        f"its error along the viewing ray has median {o['along_abs_median_mm']:.1f} mm and 75th "
        f"percentile {o['along_abs_p75_mm']:.1f} mm ({100 * o['along_over_10mm']:.0f} % above "
        f"10 mm), across it median {o['lateral_median_mm']:.1f} mm; its rotation error median "
        f"{o['rotation_median_deg']:.1f} deg, with {100 * o['flip_rate']:.1f} % flips (over 30 "
        f"deg); {100 * o['far_rate']:.1f} % of its best-scored rows are more than 10 cm off, "
        f"and {100 * r['miss_rate']:.1f} % of the {r['targets']} targets have no row"
    ]


#: Sentences that quote figures, by name.
QUOTES = {
    q.name: q
    for q in (
        Quote(
            "readme-realistic",
            "README.md",
            ("t1-structure-realistic-ssp", "t1-isolated-realistic-ssp"),
            _readme_realistic,
        ),
        Quote(
            "readme-baselines",
            "README.md",
            _realistic("structure") + _realistic("isolated"),
            _readme_baselines,
        ),
        Quote(
            "readme-paper",
            "README.md",
            ("t1-isolated-paper-ssp", "t1-structure-paper-ssp"),
            _readme_paper,
        ),
        Quote(
            "readme-estimated",
            "README.md",
            ("t1-isolated-estimated", "t1-structure-estimated"),
            _readme_estimated,
        ),
        Quote(
            "benchmarks-rgb-calibration",
            "docs/benchmarks.md",
            ("rgb-calibration",),
            _rgb_calibration,
        ),
        Quote(
            "readme-tower",
            "README.md",
            FIGURES["tower-realistic"].sources + FIGURES["tower-structure"].sources,
            _readme_tower,
        ),
    )  # fmt: skip
}


# ------------------------------------------------------------------------------ files
def load(root: Path) -> Results:
    """The results of every source present under ``root/docs/results``."""
    out = {}
    for s in SOURCES.values():
        p = root / RESULTS / s.name / s.file
        if p.is_file():
            out[s.name] = json.loads(p.read_text(encoding="utf-8"))
    return out


def doc_files(root: Path) -> list[Path]:
    """README.md and docs/*.md: the files that may hold figure blocks."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def blocks(text: str, where: str) -> list[tuple[str, int, int]]:
    """The marked blocks of a file: (name, first line, end marker line), 0-based; a marker
    left open or a stray end marker raises :class:`~ssp.errors.SSPError`."""
    out, lines, open_ = [], text.splitlines(), None
    for i, s in enumerate(lines):
        m = BEGIN.match(s.strip())
        if m:
            if open_ is not None:
                raise SSPError(f"{where}:{i + 1}: figures {m.group(1)} opens inside {open_[0]}")
            open_ = (m.group(1), i)
        elif s.strip() == END:
            if open_ is None:
                raise SSPError(f"{where}:{i + 1}: {END} without an opening marker")
            out.append((open_[0], open_[1] + 1, i))
            open_ = None
    if open_ is not None:
        raise SSPError(f"{where}:{open_[1] + 1}: figures {open_[0]} is never closed")
    return out


def _body(lines: list[str]) -> list[str]:
    while lines and not lines[0].strip():
        lines = lines[1:]
    while lines and not lines[-1].strip():
        lines = lines[:-1]
    return lines


def _plain(s: str) -> str:
    return s.replace("**", "")


def _missing(fig: Figure | Quote, results: Results) -> list[str]:
    return [s for s in fig.sources if s not in results]


def _incomplete(where: str, name: str, missing: list[str]) -> Problem:
    files = ", ".join(f"{RESULTS}/{s}/{SOURCES[s].file}" for s in missing)
    return Problem(
        "incomplete",
        where,
        f"{name}: no results file {files}: run examples/docs_figures.sh",
        missing,
    )


def _check_block(fig: Figure, body: list[str], results: Results, where: str) -> list[Problem]:
    rendered, missing = fig.render(results), _missing(fig, results)
    if not missing:
        if rendered == body:
            return []
        k = next((i for i, (a, b) in enumerate(zip(body, rendered, strict=False)) if a != b), None)
        if k is None:
            k = min(len(body), len(rendered))
        got = body[k] if k < len(body) else "(end)"
        want = rendered[k] if k < len(rendered) else "(end)"
        return [Problem("differs", where, f"figures {fig.name} differ at its line {k + 1}: the "
                        f"docs say {got!r}, its results {want!r}: run `ssp bench docs-figures "
                        "--write`")]  # fmt: skip
    have = {_plain(s) for s in body}
    out = [
        Problem("differs", where, f"figures {fig.name}: the row {_plain(row)!r} of its results "
                "present is not in the docs")
        for row in rendered[2:] if _plain(row) not in have
    ]  # fmt: skip
    return [*out, _incomplete(where, f"figures {fig.name}", missing)]


def _check_quote(q: Quote, text: str, results: Results) -> list[Problem]:
    missing = _missing(q, results)
    if missing:
        return [_incomplete(q.file, f"sentence {q.name}", missing)]
    flat = re.sub(r"\s+", " ", text)
    return [
        Problem("differs", q.file, f"sentence {q.name}: {s!r} (from its results) is not in it")
        for s in q.render(results)
        if s not in flat
    ]


def check(root: Path) -> list[Problem]:
    """Every problem of the docs under ``root``: a marked block whose text is not what its
    results render to (``differs``), a block of an unknown name (``unknown``), a sentence of
    :data:`QUOTES` not in its file (``differs``); and every figure or sentence whose results
    are not all present (``incomplete``: the rows of the results present are checked all the
    same)."""
    results = load(root)
    problems: list[Problem] = []
    for path in doc_files(root):
        where = str(path.relative_to(root))
        lines = path.read_text(encoding="utf-8").splitlines()
        for name, first, end in blocks("\n".join(lines), where):
            fig = FIGURES.get(name)
            if fig is None:
                problems.append(Problem("unknown", where, f"no figures named {name}"))
                continue
            problems += _check_block(fig, _body(lines[first:end]), results, where)
    for q in QUOTES.values():
        problems += _check_quote(q, (root / q.file).read_text(encoding="utf-8"), results)
    return problems


def write(root: Path) -> list[str]:
    """Render every marked block whose results are all present into its file; the names of
    the blocks that changed."""
    results, changed = load(root), []
    for path in doc_files(root):
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        for name, first, end in reversed(blocks(text, str(path))):
            fig = FIGURES.get(name)
            if fig is None or _missing(fig, results):
                continue
            new = ["", *fig.render(results), ""]
            if lines[first:end] != new:
                lines[first:end] = new
                changed.append(name)
        new_text = "\n".join(lines) + ("\n" if text.endswith("\n") else "")
        if new_text != text:
            atomic_write_text(path, new_text)
    return changed


def collect(work: Path, root: Path) -> list[Path]:
    """Copy ``work/<source>/<file>`` of every source present into ``root/docs/results``,
    without the per-object and per-frame records (a Table I run's ``records``,
    ``estimator_records`` and ``camera.rows``, a camera bench's ``rows`` per path and
    tracker); the files written."""
    written = []
    for s in SOURCES.values():
        src = work / s.name / s.file
        if not src.is_file():
            continue
        data = json.loads(src.read_text(encoding="utf-8"))
        for key in ("records", "estimator_records"):
            data.pop(key, None)
        if isinstance(data.get("camera"), dict):
            data["camera"].pop("rows", None)
        for trackers in (data.get("paths") or {}).values():
            for summary in trackers.values():
                summary.pop("rows", None)
        dest = root / RESULTS / s.name / s.file
        dest.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(dest, json.dumps(data, indent=1) + "\n")
        written.append(dest)
    return written
