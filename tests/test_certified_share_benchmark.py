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


def test_inputs_row_splits_the_looseness_and_the_radius_holds_every_sampled_remainder(
    monkeypatch,
):
    monkeypatch.setattr(share, "INPUT_SAMPLES", 40)
    row = share.inputs_row("ur5e_friction", 0.55, None)
    assert row["pieces"] == 1 and row["samples_per_piece"] == 80
    for sensor in ("encoder", "tachometer"):
        # every sampled remainder lies within r_k (entrywise), so every percentile is >= 1
        median, p90 = row[f"{sensor}_cert"]
        assert 1.0 <= median <= p90 < 1e3, (sensor, row)
        for key in ("indep", "enclosure"):
            low, high = row[f"{sensor}_{key}"]
            assert 0.0 < low <= high < 1e3, (sensor, key, row)
    shares = row["w_share"]
    assert set(shares) == {*share.BLOCK_GROUPS, *share.REST_PARTS}
    for key, (median, p90) in shares.items():
        # parts of w_k: within [0, 1] (up to the rounding of the division)
        assert -1e-9 <= median <= p90 <= 1.0 + 1e-9, (key, row)
    # the parts add up to w_k: what is left is the inflation factors (the checker's margin,
    # certified._CHECK_MARGIN = 1e-7, and a few ulps), 0 at the 3 decimals reported
    assert abs(shares["rest"][0]) < 1e-9 and abs(shares["rest"][1]) < 1e-9, row
    # on a friction box w_k comes from the parameters' block (their effect through the
    # state they move, e.g. the Coulomb sign's curvature), not from the remainder's
    assert shares["parameter_parameter"][0] > 0.5, row


def test_products_row_attributes_the_error_term_to_the_products():
    row = share.products_row("ur5e_friction", 0.1, None)
    assert row["pieces"] == 1 and row["step"] == 10
    for block in ("dd", "all"):
        dropped, certifier, plain = (
            row[f"{v}_e_{block}"] for v in ("no_quadratic", "certifier", "plain")
        )
        # the products' quadratic parts are part of the error term, and the certifier's
        # polarisation bound is below the plain product of radii
        assert 0.0 <= dropped < certifier < plain, row
        # the linear parts do not depend on how the quadratic part is bounded (the
        # centres move them a little)
        lin = [row[f"{v}_lin_{block}"] for v in share.PRODUCT_VARIANTS]
        assert max(lin) <= 1.1 * min(lin), row
        # carried in pair symbols, the quadratic parts leave the error term; on this short,
        # nearly linear run (error terms 4 % of the radius) the pair symbols' coefficients
        # cost about as much as they save (the whole box: docs/methods.md)
        assert row[f"paired_e_{block}"] < 0.5 * row[f"certifier_e_{block}"], row
        assert row[f"paired_rad_{block}"] < 1.02 * row[f"certifier_rad_{block}"], row
