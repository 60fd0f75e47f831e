"""Result bundles: runs exported from one results store, verified against the ground truth
vprbench ships, and merged into a results repository that many contributors feed.

    export.py      one archive of records, per-query arrays, method cards and sha256 sums
    verify.py      every record re-scored from its arrays; hostile archives refused
    repository.py  verified bundles merged into a folder laid out by identity; every run of it re-scored;
                   a cache's runs with a repository's (read_runs: what every leaderboard is built from)
    vpr_bench.py   VPR-Bench's precomputed matches turned into re-scored records
"""
from .export import export_bundle, select_records
from .repository import import_bundles, read_repository, read_runs, verify_repository
from .verify import verify_bundle

__all__ = ["export_bundle", "import_bundles", "read_repository", "read_runs", "select_records", "verify_bundle", "verify_repository"]
