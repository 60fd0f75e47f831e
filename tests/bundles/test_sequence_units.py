"""A real sequence run on Corridor: its record states blocks that cover its window, and verify
derives the same units from the record's stages (so it accepts the record) yet still refuses units
forged into its arrays."""
from __future__ import annotations

import numpy as np
import pytest
from bundle_files import edit_arrays, read_bundle, write_bundle

from vprbench.bundles import export_bundle, verify_bundle
from vprbench.evaluation.rescore import DataGroundTruth
from vprbench.evaluation import evaluate, read_results, save_result
from vprbench.spec import RunSettings, resolve_spec


@pytest.fixture(scope="module")
def sequence_bundle(shared_data, tmp_path_factory):
    cache = tmp_path_factory.mktemp("sequence-store")
    spec = resolve_spec("hog", "corridor", stages=[{"name": "diagonal", "length": 10, "mode": "causal"}],
                        data_dir=shared_data, cache_dir=cache)
    save_result(evaluate(spec, RunSettings(cache_dir=cache, data_dir=shared_data, workers=0)), cache)
    [record] = read_results(cache)
    return export_bundle([record], cache / "seq.tar.gz"), record


def test_verify_accepts_a_sequence_record_with_its_longer_blocks(sequence_bundle, shared_data):
    bundle, record = sequence_bundle
    assert record["track"] == "sequence"
    assert record["resampling"]["block_length"] == 14 and record["resampling"]["query_window"] == 10  # 2 * 2 + 10
    report = verify_bundle(bundle, DataGroundTruth(shared_data))
    assert report.ok, report.lines()


def test_verify_refuses_a_traverse_order_forged_into_a_sequence_record(sequence_bundle, shared_data, tmp_path):
    bundle, _ = sequence_bundle
    members = read_bundle(bundle)
    edit_arrays(members, lambda arrays: arrays.update(order=np.arange(111, dtype=np.int32)[::-1].copy()))
    report = verify_bundle(write_bundle(tmp_path / "forged.tar.gz", members), DataGroundTruth(shared_data))
    assert not report.ok
    [problem] = [p for v in report.verdicts for p in v.problems]
    assert "its bootstrap units (blocks of 14 consecutive queries, covering a sequence window of 10) are not those " \
           "of protocol" in problem and "its intervals would be drawn from the wrong units" in problem
