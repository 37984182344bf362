"""benchmarks/certified_share.py: the nested widths it reports are nested, and the
sampled runs stay within each piece's remainder radius (the certificate's soundness,
seen through the diagnostic)."""

from helpers import load_benchmark

share = load_benchmark("certified_share")


def test_widths_are_nested_and_the_remainder_holds_the_samples():
    row = share.share_row("pendulum_sine", 0.6, None)
    assert row["pieces"] == 4 and row["samples"] > 1000
    for sensor in ("encoder", "tachometer"):
        sampled, bound, band = (
            row[f"{sensor}_{k}"] for k in ("poly_sampled", "poly_bound", "band")
        )
        # medians and p90s of entrywise nested ratios are nested
        for i in range(2):
            assert 0.9 < sampled[i] <= bound[i] <= band[i] < 1.5, (sensor, row)
        low, high = row[f"{sensor}_remainder_share"]
        assert 0.0 < low <= high < 1.0
        seen_median, seen_p90 = row[f"{sensor}_remainder_seen"]
        # inside the radius (a run outside would exceed 1), and not vacuous: the runs
        # do move away from the polynomial
        assert 0.0 < seen_median <= seen_p90 <= 1.0
