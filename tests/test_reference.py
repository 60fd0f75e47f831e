"""The shipped paper numbers: complete, and consistent across the paper's own tables."""
import pytest

from vprbench.reference import paper_results


def test_tables_ii_and_iii_are_complete():
    ii, iii = paper_results(table="II"), paper_results(table="III")
    assert ii.groupby("metric").size().to_dict() == {"r1": 66, "r5": 66}  # 11 methods x 6 datasets
    assert set(iii["column"]) == {"hawkins", "laurel-caverns", "mid-atlantic-ridge", "nardo-air", "nardo-air-r", "vp-air"}
    assert ii[(ii.row == "AnyLoc-VLAD-DINOv2") & (ii.column == "baidu-mall") & (ii.metric == "r1")].value.item() == 75.2


@pytest.mark.parametrize("domain, datasets", [
    ("indoor", ["baidu-mall", "gardens-point", "17places"]),
    ("urban", ["pitts30k", "st-lucia", "oxford"]),
    ("aerial", ["nardo-air", "nardo-air-r", "vp-air"]),
])
def test_table_iv_domain_row_is_the_mean_of_tables_ii_and_iii(domain, datasets):
    main = paper_results()
    main = main[main.table.isin(["II", "III"]) & (main.row == "AnyLoc-VLAD-DINOv2") & (main.metric == "r1")]
    mean = main[main.column.isin(datasets)].value.mean()
    iv = paper_results(table="IV")
    reported = iv[(iv.row == "Domain-Specific") & (iv.column == domain)].value.item()
    # each value is rounded to 0.1, so the mean of rounded values and the rounded mean differ by <= 0.1
    assert mean == pytest.approx(reported, abs=0.1)
