"""`vprbench datasets verify NAME`: is the dataset on disk complete and readable?

Checks, in order, and reports exactly what is missing or wrong: the folder, the layout's
expected folders and files, the image and query counts against the manifest (a warning, an
error with strict), the ground truth (readable, one entry per query, indices inside the
database), and a sample of images (decoded; all of them when sample is None).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import VPRBenchError
from ..images import load_image
from ..paths import resolved
from ..text import one_line, plural, quantity
from .layouts import candidates, describe_layout, detect_layout, missing_paths, read_layout
from .layouts.base import MissingPart
from .layouts.own_data import own_manifest
from .layouts.utm_zones import zone_names
from .locations import dataset_location, how_to_get
from .manifest import dataset_manifest, is_path
from .storage import BY_POSITION, absent_or_empty, by_position


@dataclass
class VerifyReport:
    name: str
    root: Path
    layout: str = ""
    problems: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    #: what reading the copy did that its counts do not show (positives dropped by the layout's rule)
    notes: list[str] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    images_checked: int = 0
    #: of them, those that did not decode (each named in problems)
    images_failed: int = 0
    #: the UTM zones the positions span, when more than one (positives never join two)
    zones: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def lines(self) -> list[str]:
        # one line each: a path or name holding a newline (a file named so) cannot split a problem in two
        head = f"{self.name}: {'OK' if self.ok else 'PROBLEMS'} at {one_line(self.root)}" + (
            f" (layout {self.layout})" if self.layout else "")
        body = [f"  error: {one_line(p)}" for p in self.problems] + [f"  warning: {one_line(w)}" for w in self.warnings] \
            + [f"  note: {one_line(n)}" for n in self.notes]
        if self.summary:
            s = self.summary
            body.append(
                f"  {s['database']} database, {plural(s['queries'], 'query')}, {s['queries_with_positives']} with a positive, "
                f"{plural(s['positive_pairs'], 'positive pair')} ({s['unit']}, radius {quantity(s['radius'], s.get('radius_unit'))}); "
                + (f"{plural(self.images_checked, 'image')} decoded" if not self.images_failed else
                   f"{self.images_checked - self.images_failed} of {plural(self.images_checked, 'image')} decoded")
            )
            if self.zones:
                body.append(f"  positions span {len(self.zones)} UTM zones ({', '.join(self.zones)}); "
                            "positives are within one zone")
        return [head, *body]


def sample_paths(paths: list[Path], sample: int | None) -> list[Path]:
    """Evenly spaced (deterministic) sample, always including the first and last."""
    if sample is None or sample >= len(paths):
        return list(paths)
    return [paths[i] for i in np.unique(np.linspace(0, len(paths) - 1, sample).round().astype(int))]


def verify_dataset(name: str, data_dir=None, strict: bool = False, sample: int | None = 20) -> VerifyReport:
    """`name` is a dataset name, or a folder of the user's own data (a path)."""
    if sample is not None and sample < 0:
        raise VPRBenchError(f"--sample must be 0 or more images per split, got {sample}")
    if is_path(name):  # the rule every command reads a name by
        root = resolved(name, "The folder to verify")  # shown as the folder it is, not as typed
        if not root.is_dir():
            problem = f"{root} is a file, not a folder" if root.exists() else f"folder {root} does not exist"
            return VerifyReport(name=name, root=root, problems=[problem])
        manifest = own_manifest(root)
    else:
        manifest = dataset_manifest(name)
        root = dataset_location(manifest, data_dir)
    report = VerifyReport(name=manifest.name, root=root)  # own data: its dataset.toml name, not the path given
    if not root.is_dir():
        report.problems.append(f"folder {root} does not exist. {how_to_get(manifest, data_dir)}")
        return report
    try:
        chosen = detect_layout(root, manifest)
    except VPRBenchError:
        for candidate in candidates(manifest):
            report.problems.append(f"{describe_layout(candidate)} is missing: {', '.join(missing_paths(root, candidate))}")
        return report
    report.layout = chosen.layout
    try:
        dataset = read_layout(root, manifest, data_dir)
    except MissingPart as error:  # without its advice to run this very check
        report.problems.append(error.detail)
        return report
    except VPRBenchError as error:
        report.problems.append(str(error))
        return report
    for split, expected, paths in (("database", chosen.database_count, dataset.database), ("query", chosen.query_count, dataset.queries)):
        if expected is not None and expected != len(paths):
            message = f"{len(paths)} {split} images, the manifest expects {expected} ({expected - len(paths):+d})"
            shifted = split == "database" and by_position(dataset)
            if shifted:
                message += f". {BY_POSITION} use a complete copy"
            (report.problems if strict or shifted else report.warnings).append(message)
    report.notes = [n for n in dataset.notes if n != manifest.notes]
    absent = absent_or_empty(dataset.database + dataset.queries)
    if absent:
        report.problems.append(absent)
    try:
        report.summary = dataset.summary()
    except VPRBenchError as error:
        report.problems.append(str(error))
    else:
        gt = dataset.ground_truth
        if gt.query_zones is not None:
            zones = zone_names(np.concatenate([gt.database_zones, gt.query_zones]))
            report.zones = zones if len(zones) > 1 else []
        without = report.summary["queries"] - report.summary["queries_with_positives"]
        if without:
            report.warnings.append(f"{plural(without, 'query')} without a positive (counted as failures in Recall@K)")
    for path in sample_paths(dataset.database, sample) + sample_paths(dataset.queries, sample):
        if path.is_file():
            try:
                load_image(path)
            except VPRBenchError as error:
                report.problems.append(str(error))
                report.images_failed += 1
            report.images_checked += 1
    return report
