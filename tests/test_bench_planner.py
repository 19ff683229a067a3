"""`gpmppi bench planner --online-weights`: the weights move every iteration and go through `Planner.prepare`
first (as in the planner service), a fixed-weight planner runs interleaved, and both ratios are reported."""

from __future__ import annotations

import pytest

from tools.bench_planner import run_bench


@pytest.mark.parametrize("prepare", [True, False])
def test_online_weights_report_the_fixed_weight_plan_and_the_collapse_ahead(prepare: bool) -> None:
    res = run_bench(64, 5, "gp", "grid", "cpu", None, iters=4, warmup=2, online_weights=True, prepare=prepare)
    assert res["online_weights"] and res["prepare"] is prepare
    assert res["fixed_p50_ms"] > 0
    assert res["ratio_moving_vs_fixed"] == pytest.approx(res["p50_ms"] / res["fixed_p50_ms"])
    if prepare:
        assert res["prepare_p50_ms"] > 0
        assert res["ratio_cycle_vs_fixed"] > res["ratio_moving_vs_fixed"]
    else:
        assert res["prepare_p50_ms"] == 0 and res["ratio_cycle_vs_fixed"] == res["ratio_moving_vs_fixed"]
