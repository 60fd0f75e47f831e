"""What a contributed record says beside its numbers, checked against what decides it.

Re-scoring proves a record's metrics; the names around them choose where the numbers land and
what they are called: the method and label name the row, the dataset, protocol and domain the
column and the table (structured or not), the weights whether the row is official. Each must be
what the record's own spec says, or what vprbench ships for its protocol hash; a record that
says otherwise claims a run it did not make, and is refused. So is a second record under a run id,
and a method card (methods/<row key>.json) that describes another method than its records.
"""
from __future__ import annotations

import json

from ..evaluation.results import card_of
from ..spec import RunSpec
from .export import CARDS


def false_claims(record: dict) -> list[str]:
    """One line per name the record gives that its spec or vprbench's manifests contradict."""
    from ..datasets import dataset_manifests
    from ..evaluation.identity import benchmark_protocols
    from ..stages.registry import available_stages
    from ..weights import is_file_identity, weights_provenance

    spec = RunSpec.model_validate(record["spec"])
    # a stage's label leaves out its defaults, known only where its plugin is installed
    missing = [stage.name for stage in spec.stages if stage.name not in available_stages()]
    protocol = record["protocol"]
    given = [("method", record["method"], spec.method, "its spec"),
             ("label", record.get("label", spec.label()), spec.label(), "its spec"),
             ("dataset", record["dataset"], spec.dataset.name, "its spec"),
             ("dataset kind", record["dataset_kind"], spec.dataset.kind, "its spec"),
             ("protocol id", protocol["id"], spec.dataset.protocol_id, "its spec"),
             ("protocol name", protocol.get("name"), spec.dataset.protocol, "its spec")]
    shipped = benchmark_protocols(record["dataset"]).get(protocol["hash"])
    if shipped is not None:  # else no benchmark protocol: the ground truth step names it
        as_shipped = f"protocol {protocol['hash']} as vprbench ships it"
        given += [("protocol id", protocol["id"], shipped["id"], as_shipped),
                  ("protocol name", protocol.get("name"), shipped["name"], as_shipped),
                  ("domain", record.get("domain"), dataset_manifests()[record["dataset"]].domain,
                   f"the {record['dataset']} manifest")]
    weights = spec.files.get("weights")
    if is_file_identity(weights):  # a weights file, known by its content (a malformed one is no file's)
        stated = ((record.get("provenance") or {}).get("weights") or {}).get("source")
        given.append(("weights source", stated, weights_provenance(weights)["source"],
                      f"its weights file {weights[:19]}"))
    problems = [f"it says {what} {claimed!r}, but {source} says {truth!r}; a record names only the run it made"
                for what, claimed, truth, source in given if claimed != truth and not (what == "label" and missing)]
    if missing and record.get("label", spec.label()) != spec.label():
        problems.append(f"its stage {', '.join(missing)} is not installed here, so its label cannot be checked: install "
                        "the package that provides it ('vprbench stages list' shows what is installed), then verify again")
    return problems


def one_record_per_run(verdicts: list) -> None:
    """A run id names one run (pages and `results export --run` find it by its id alone): a second
    record under it, in another row or protocol folder, is refused."""
    first: dict[str, str] = {}
    for verdict in verdicts:
        if verdict.run_id in first:
            verdict.problems.append(f"its run id is also that of {first[verdict.run_id]}; a run id names one run")
        first.setdefault(verdict.run_id, verdict.member)


def false_card(data: bytes, record: dict) -> list[str]:
    """The row's method card (stored beside the runs, once per row) describes the record's method:
    each field the record decides that the card has must be the record's."""
    why = card_disagreement(data, record)
    return [f"its method card {CARDS}/{record['row_key']}.json {why}"] if why else []


def card_disagreement(data: bytes, record: dict) -> str | None:
    """How the card `data` fails to describe `record` ("disagrees with the record on label, ..."), None when
    it describes it."""
    try:
        card = json.loads(data)
    except (ValueError, RecursionError):
        card = None
    if not isinstance(card, dict):
        return "is not a JSON object"
    wrong = [key for key, value in card_of(record).items() if key in card and card[key] != value]
    return f"disagrees with the record on {', '.join(wrong)}" if wrong else None
