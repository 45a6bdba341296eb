"""Markdown of a benchmark run (``results.md``) and of the difference between two runs."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from .datasets import SEEDED, TIERS, unswapped
from .metrics import PRECISE_PX, SHARED_WALL_GROUPS, SUCCESS_PX

__all__ = ["results_markdown", "compare_summaries", "compare_cases", "outcome", "options_text", "COMPARED"]

#: Summary fields that :func:`compare_summaries` shows: (key, label, kind).
COMPARED = (
    ("success_rate", "success", "rate"),
    ("precise_rate", "precise", "rate"),
    ("declined_rate", "declined", "rate"),
    ("wrong_rate", "wrong", "rate"),
    ("false_merge_rate", "false merges", "rate"),
    ("median_error_px", "median error (px)", "num"),
    ("median_time_s", "median time (s)", "num"),
    ("max_peak_mb", "peak MB", "num"),
)


def _params(params) -> str:
    def text(k, v):
        if k == "source_maps":  # file names here; config.json has their paths and digests
            return "source maps " + " ".join(Path(m["path"]).name for m in v)
        return f"{k.replace('_', ' ')} {v}"

    return "".join(", " + text(k, v) for k, v in (params or {}).items())


def _pct(rate: Optional[float], k: Optional[int] = None, n: Optional[int] = None) -> str:
    if rate is None:
        return "–"
    s = f"{100 * rate:.0f} %"
    return f"{s} ({k}/{n})" if k is not None and n is not None else s


def _num(v: Optional[float], digits: int = 2) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def _table(header: list, rows: list) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(" --- " for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def _summary_row(r: dict, first: list) -> list:
    return first + [
        r["positives"],
        _pct(r["success_rate"], r["success"], r["positives"]),
        "–" if not r["positives"] else _pct(r["precise_rate"]) if r["precise_rate"] is not None else "n/a",
        _pct(r["declined_rate"], r["declined"], r["positives"]),
        r.get("declined_right_candidate", "–") if r["positives"] else "–",
        _pct(r["wrong_rate"], r["wrong"], r["positives"]),
        _pct(r["false_merge_rate"], r["false_merges"], r["negatives"]) if r["negatives"] else "–",
        _num(r["median_error_px"]),
        _num(r["p90_error_px"]),
        _num(r["median_time_s"]),
        _num(r["max_time_s"]),
        _num(r["max_peak_mb"], 0),
    ]


_HEADER = [
    "positives",
    "success",
    "precise",
    "declined",
    "of which right candidate",
    "wrong",
    "false merges (negatives)",
    "median err",
    "p90 err",
    "median s",
    "max s",
    "peak MB",
]


def options_text(options: dict) -> str:
    """The AlignOptions a run changed, as Markdown (```min_confidence` = 0.4``), or ``defaults``."""
    return ", ".join(f"`{k}` = {v}" for k, v in sorted(options.items())) or "defaults"


def results_markdown(bench) -> str:
    """``results.md`` of a :class:`~gridmerge.bench.runner.BenchRun`."""
    c = bench.config
    s = bench.summary
    mach = c.get("machine", {})
    out = ["# gridmerge benchmark\n\n"]
    sets = ", ".join(f"{d['name']} ({d['cases']} cases{_params(d.get('params'))})" for d in c.get("datasets", []))
    out.append(
        f"Seed {c.get('seed')}; methods {', '.join(c.get('methods', []))}; data sets {sets}"
        + ("; quick slice" if c.get("quick") else "")
        + ".\n\n"
        f"Machine: {mach.get('platform')}, {mach.get('cpu_count')} CPUs; Python {mach.get('python')}, "
        f"numpy {mach.get('numpy')}, OpenCV {mach.get('opencv')}; gridmerge {mach.get('gridmerge')}. "
        f"Run {c.get('started')}, {c.get('duration_s')} s.\n"
    )
    if c.get("options"):
        out.append(f"\nOptions changed for gridmerge's own methods (the baselines keep their rules): {options_text(c['options'])}.\n")
    desc = c.get("method_descriptions") or {}
    if any(desc.values()):
        out.append("\nMethods:\n\n" + "".join(f"* `{m}`: {d}\n" for m, d in desc.items()))
    if s.get("warnings") or s.get("notes"):
        out.append("\n**Notes.**\n\n" + "".join(f"* {w}\n" for w in s.get("warnings", []) + s.get("notes", [])))

    rows = s.get("rows", [])
    main = [r for r in rows if r["tier"] == "all"]
    if main:
        out.append("\n## Summary\n\n")
        out.append(
            _table(["data set", "method"] + _HEADER, [_summary_row(r, [r["dataset"], f"`{r['method']}`"]) for r in main])
        )
    tiered = [r for r in rows if r["tier"] != "all"]
    for ds, by in dict.fromkeys((r["dataset"], r.get("by", "tier")) for r in tiered):
        sub = [r for r in tiered if r["dataset"] == ds and r.get("by", "tier") == by]
        order = {t: i for i, t in enumerate(list(TIERS) + ["negative"] + [label for label, _ in SHARED_WALL_GROUPS])}
        sub.sort(key=lambda r: (order.get(r["tier"], 99), r["tier"]))
        out.append(f"\n## {ds} by {by}\n\n")
        out.append(_table([by, "method"] + _HEADER, [_summary_row(r, [r["tier"], f"`{r['method']}`"]) for r in sub]))
        if unswapped(ds) == "simulated" and by == "shared walls":
            out.append(
                "\nShared walls: cells of the source map that both robots saw as walls (before noise); "
                "positive pairs only. The overlap of known cells counts open floor too, which fixes no pose.\n"
            )
        if unswapped(ds) == "simulated" and by == "tier":
            out.append(
                "\nTiers: "
                + "; ".join(
                    f"**{t.name}** overlap {t.overlap[0]:.0%}-{t.overlap[1]:.0%}, scale {t.scale[0]:.2f}-{t.scale[1]:.2f}, "
                    f"noise {t.noise:g}"
                    for t in TIERS.values()
                )
                + "; any rotation. **negative**: two distant parts of one map or two different maps (must be declined).\n"
            )
        if unswapped(ds) == "halmstad-partial" and by == "tier":
            out.append(
                "\nEach robot explored part of a building in its own real map (two Halmstad sessions); tiers as the "
                "simulated set's, without added noise. Positives are scored by the Halmstad protocol on the annotated "
                "points in the overlap. **negative**: two distant parts of the building (must be declined).\n"
            )

    t1 = s.get("table1") or {}
    if t1.get("methods"):
        out.append("\n## The paper's Table I experiment\n\n")
        tr, pp = t1["truth"], t1["paper"]
        body = [
            ["truth", tr["rotation_deg"], tr["x"], tr["y"], tr["scale"], "", ""],
            ["the paper's Table I estimate", pp["rotation_deg"], pp["x"], pp["y"], pp["scale"], "", ""],
        ]
        for m in t1["methods"]:
            if m["rotation_deg"] is None:
                body.append([f"`{m['method']}` ({m['case_id']})", "declined", "", "", "", "", ""])
                continue
            body.append(
                [
                    f"`{m['method']}` ({m['case_id']})",
                    f"{m['rotation_deg']:.4f}",
                    f"{m['x']:.3f}",
                    f"{m['y']:.3f}",
                    f"{m['scale']:.5f}",
                    f"{abs(m['rotation_deg'] - tr['rotation_deg']):.4f} / {abs(m['x'] - tr['x']):.3f} / "
                    f"{abs(m['y'] - tr['y']):.3f} / {abs(m['scale'] - tr['scale']):.5f}",
                    _num(m["corner_error_px"], 3),
                ]
            )
        out.append(
            _table(["", "rotation (deg)", "x (px)", "y (px)", "scale", "errors (rot / x / y / scale)", "corner error (px)"], body)
        )
        out.append(
            f"\nThe paper's errors: {abs(pp['rotation_deg'] - tr['rotation_deg']):.2f} deg, "
            f"{abs(pp['x'] - tr['x']):.2f} px, {abs(pp['y'] - tr['y']):.2f} px, {abs(pp['scale'] - tr['scale']):.4f}.\n"
        )

    out.append(
        "\n## Definitions\n\n"
        f"* **success**: aligned and the corner error (largest distance between the four corners of b's image "
        f"mapped by the estimate and by the truth, in a's pixels) at most {SUCCESS_PX:g} px; on the Halmstad pairs, "
        "the data set's protocol: median |T(points_b) - points_a| at most max(20 px, 2 x the annotation fit's median "
        "residual). Rates are over the positive pairs.\n"
        f"* **precise**: corner error at most {PRECISE_PX:g} px (n/a on Halmstad).\n"
        "* **declined**: no transform returned (or the method raised an error); **of which right candidate**: declined "
        "pairs whose best candidate would have been a success (declined too cautiously). **wrong**: aligned but not a success. "
        "**false merges**: negative pairs (different places) that were aligned.\n"
        "* **err**: of the successes (corner error; median point error on Halmstad). **s**: wall time of the align "
        "call (with peak MB measured, under tracemalloc, which slows the calls about 1.5-1.7x: compare the methods' "
        "times with one another). **peak MB**: tracemalloc peak during the call (numpy and Python allocations; memory "
        "that OpenCV allocates natively is not seen; the process's max RSS is in `cases.jsonl`; `--no-memory`: not "
        "measured).\n"
    )
    return "".join(out)


def _fmt(kind: str, v) -> str:
    if v is None:
        return "–"
    return f"{100 * v:.1f} %" if kind == "rate" else f"{v:.3g}"


def _delta(kind: str, a, b) -> str:
    if a is None or b is None:
        return ""
    d = b - a
    if kind == "rate":
        return f"{100 * d:+.1f} pt" if abs(d) > 1e-12 else "="
    return f"{d:+.3g}" if d != 0 else "="


def compare_summaries(run1, run2) -> str:
    """Markdown: one row per method, data set and tier of either run, each compared field
    as ``run1 → run2 (difference)``; then the cases that changed (:func:`compare_cases`)."""
    r1 = {(r["method"], r["dataset"], r["tier"]): r for r in run1.rows}
    r2 = {(r["method"], r["dataset"], r["tier"]): r for r in run2.rows}
    keys = list(dict.fromkeys(list(r1) + list(r2)))
    name1 = str(run1.out_dir) if run1.out_dir is not None else "run 1"
    name2 = str(run2.out_dir) if run2.out_dir is not None else "run 2"
    out = [f"# Benchmark comparison\n\nrun 1: {name1} (seed {run1.config.get('seed')}); run 2: {name2} (seed {run2.config.get('seed')}). "
           "Cells: run 1 → run 2 (difference).\n\n"]
    opts = run1.config.get("options") or {}, run2.config.get("options") or {}
    if opts[0] != opts[1]:
        out.append(f"Options of gridmerge's own methods: run 1 {options_text(opts[0])}; run 2 {options_text(opts[1])}.\n\n")
    header = ["data set", "tier", "method", "pairs"] + [label for _, label, _ in COMPARED]
    body = []
    for k in keys:
        a, b = r1.get(k), r2.get(k)
        pairs = f"{a['cases'] if a else '–'} → {b['cases'] if b else '–'}"
        cells = []
        for key, _, kind in COMPARED:
            va = None if a is None else a.get(key)
            vb = None if b is None else b.get(key)
            d = _delta(kind, va, vb)
            cells.append(f"{_fmt(kind, va)} → {_fmt(kind, vb)}" + (f" ({d})" if d else ""))
        body.append([k[1], k[2], f"`{k[0]}`", pairs] + cells)
    out.append(_table(header, body))
    for label, mine, other in (("run 1", r1, r2), ("run 2", r2, r1)):
        only = [k for k in mine if k not in other]
        if only:
            out.append(f"\nOnly in {label}: {_methods_on(only)}.\n")
    seeds = run1.config.get("seed"), run2.config.get("seed")
    if seeds[0] == seeds[1]:
        out.append(compare_cases(run1.records, run2.records))
    else:
        # A simulated case of one id is another pair under another seed.
        def fixed(records):
            return [r for r in records if unswapped(r["dataset"]) not in SEEDED]

        out.append(compare_cases(fixed(run1.records), fixed(run2.records)))
        out.append(f"\nThe runs' seeds differ ({seeds[0]} and {seeds[1]}): simulated and partial cases are not compared "
                   "case by case.\n")
    return "".join(out)


def _methods_on(keys) -> str:
    """```a`, `b` on simulated, halmstad; `c` on paper``: the methods of summary rows
    ``(method, dataset, tier)``, those with the same data sets together (tiers left out)."""
    sets: dict = {}
    for m, d, _ in keys:
        sets.setdefault(m, [])
        if d not in sets[m]:
            sets[m].append(d)
    groups: dict = {}
    for m, ds in sets.items():
        groups.setdefault(tuple(ds), []).append(m)
    return "; ".join(", ".join(f"`{m}`" for m in ms) + " on " + ", ".join(ds) for ds, ms in groups.items())


#: How far a case's error must move, with its outcome unchanged, to be listed (pixels).
MOVED_PX = 1.0
#: At most this many cases are listed in each table of :func:`compare_cases`.
LISTED_CASES = 30


def outcome(record: dict) -> str:
    """``"right"``, ``"wrong"`` or ``"declined"`` for a positive pair; ``"false merge"``
    or ``"declined"`` for a negative one."""
    if not record["positive"]:
        return "false merge" if record["false_merge"] else "declined"
    return "right" if record["success"] else "wrong" if record["wrong"] else "declined"


def _error(record: dict):
    e = record.get("point_error_px")
    return record.get("corner_error_px") if e is None else e


def compare_cases(records1: list, records2: list) -> str:
    """Markdown: the cases of both runs (same method and case id) whose outcome
    (:func:`outcome`) changed, and those whose error moved by more than
    :data:`MOVED_PX` with the same outcome, each with its confidence and error in both
    runs; a line saying so when the two runs agree case by case."""
    one = {(r["method"], r["case_id"]): r for r in records1}
    both = [(one[(r["method"], r["case_id"])], r) for r in records2 if (r["method"], r["case_id"]) in one]
    changed = [(a, b) for a, b in both if outcome(a) != outcome(b)]
    moved = []
    for a, b in both:
        ea, eb = _error(a), _error(b)
        if outcome(a) == outcome(b) and ea is not None and eb is not None and abs(eb - ea) > MOVED_PX:
            moved.append((a, b))
    moved.sort(key=lambda ab: -abs(_error(ab[1]) - _error(ab[0])))
    out = [f"\n## Case by case\n\nCases in both runs: {len(both)}; outcome changed: {len(changed)}; "
           f"outcome kept, error moved by more than {MOVED_PX:g} px: {len(moved)}.\n"]

    for title, pairs in (("Changed outcome", changed), (f"Error moved by more than {MOVED_PX:g} px", moved)):
        if not pairs:
            continue
        body = [[f"`{a['method']}`", a["case_id"], f"{outcome(a)} → {outcome(b)}",
                 f"{_num(a.get('confidence'))} → {_num(b.get('confidence'))}", f"{_num(_error(a), 1)} → {_num(_error(b), 1)}"]
                for a, b in pairs[:LISTED_CASES]]
        out.append(f"\n### {title}\n\n")
        out.append(_table(["method", "case", "outcome", "confidence", "error (px)"], body))
        if len(pairs) > LISTED_CASES:
            out.append(f"\n... and {len(pairs) - LISTED_CASES} more.\n")
    return "".join(out)
