"""Shared printing for benchmarks: a table beside the reference's figures, then one JSON line."""

from __future__ import annotations

import json
import os
import platform


def figure(name: str, value: float, unit: str, reference: float | None = None, *, lower_is_better: bool = True) -> dict:
    ratio = None
    if reference not in (None, 0) and value not in (None, 0):
        ratio = reference / value if lower_is_better else value / reference
    return {"name": name, "value": value, "unit": unit, "reference": reference, "ratio_vs_reference": ratio}


def report(benchmark: str, figures: list[dict], **context) -> None:
    print(f"\n{benchmark}  ({platform.processor() or platform.machine()}, {os.cpu_count()} cores)")
    print(f"{'figure':44s} {'value':>10s} {'unit':>6s} {'reference':>10s} {'x better':>9s}")
    for f in figures:
        ref = "-" if f["reference"] is None else f"{f['reference']:.3g}"
        ratio = "-" if f["ratio_vs_reference"] is None else f"{f['ratio_vs_reference']:.2f}"
        print(f"{f['name']:44s} {f['value']:10.3f} {f['unit']:>6s} {ref:>10s} {ratio:>9s}")
    print(json.dumps({"benchmark": benchmark, **context, "figures": {f"{f['name']}_{f['unit']}": {"value": f["value"], "reference": f["reference"], "ratio": f["ratio_vs_reference"]} for f in figures}}))
