"""What a run's spec asks of AnyLoc's options before the method is created: what they name in the
cache, the values unset ones stand for, the ones the aggregation leaves idle. Classmethods of AnyLoc
(`cls` is the class)."""
from __future__ import annotations

import warnings

from ..errors import VPRBenchError
from .anyloc_vocabulary import bare_folder_identity, domain_datasets, named_identity, names_file, vocabulary_policies

AGGREGATIONS = ("vlad", "vlad-soft-official", "vlad-soft", "gem", "gap", "gmp", "cls")
VLADS = ("vlad", "vlad-soft-official", "vlad-soft")
#: what PCA-whitening is fitted on: the evaluated database, or its domain's databases stacked (the authors' code)
PCA_ON = ("database", "domain")


def cached_identities(cls, options: dict, dataset: str, cache_dir=None) -> dict[str, str]:
    """A vocabulary named by source ("urban", "domain"), by the content it resolves to now."""
    vocabulary = options.get("vocabulary", "map")
    if options.get("aggregation", "vlad") not in VLADS or not isinstance(vocabulary, str) or vocabulary == "map":
        return {}
    if names_file(vocabulary):
        return bare_folder_identity(vocabulary)
    made = probe(cls, options, cache_dir)  # the settings vocabularies are keyed by
    found = made and named_identity(vocabulary, dataset, made.vocabulary_backbone, made.layer, made.facet,
                                    made.clusters, cache_dir, made.stride)
    return {"vocabulary": found} if found else {}


def implied_options(cls, options: dict) -> dict:
    """The block and stride an unset `layer`/`stride` stand for on this backbone."""
    made = probe(cls, {k: v for k, v in options.items() if k not in ("layer", "stride")})
    return {"layer": made.layer, "stride": made.stride} if made else {}


def unused_options(cls, options: dict) -> dict[str, str]:
    """Options the aggregation ignores, and why (given, they would only name the row)."""
    aggregation = options.get("aggregation", "vlad")
    vlad_only = {} if aggregation in VLADS else dict.fromkeys(("clusters", "vocabulary"), f"only VLAD uses it, "
                                                               f"the aggregation is {aggregation}")
    gem_only = {} if aggregation == "gem" else {"gem_p": f"only GeM uses it, the aggregation is {aggregation}"}
    made = probe(cls, options) if aggregation == "cls" else None  # None too for a backbone it refuses
    no_block = dict.fromkeys(("layer", "layer_for", "facet"), "the CLS token comes from the final norm, after the "
                             "last block") if made and made.spec.cls == "final-norm" else {}
    no_pca = {} if options.get("pca_dim") else {"pca_on": "only PCA-whitening uses it, pca_dim is unset"}
    return vlad_only | gem_only | no_block | no_pca


def pca_datasets(pca_on: str, dataset: str | None) -> tuple[str, list[str]] | None:
    """(domain, its datasets) whose databases PCA-whitening is fitted on, stacked (None: the evaluated
    database alone): with "domain", the evaluated dataset's vocabulary domain, as the authors'
    joint_pca_project.py."""
    if pca_on == "database":
        return None
    if dataset is None:
        raise VPRBenchError("anyloc: option pca_on=domain fits PCA on the databases of the evaluated dataset's "
                            "domain; it needs that dataset: run it with `vprbench evaluate`, or use pca_on=database.")
    domains = vocabulary_policies()["domains"]
    found = [domain for domain, members in domains.items() if dataset in (name for name, _ in members)]
    if not found:
        raise VPRBenchError(f"anyloc: option pca_on=domain: dataset {dataset!r} is in no domain (domains: "
                            f"{', '.join(domains)}); use pca_on=database.")
    return found[0], [name for name, _ in domain_datasets(found[0])]


def pca_provenance(dim: int, pca_on: str, dataset: str | None) -> dict:
    """What the record says PCA-whitening was fitted on (the evaluated database is always among it)."""
    joint = pca_datasets(pca_on, dataset)
    return {"dim": dim, "fitted_on_evaluated_database": True, "fitted_on": (
        f"the databases of the {joint[0]} domain stacked: {', '.join(joint[1])}" if joint
        else "the evaluated database's descriptors"), **({"datasets": joint[1]} if joint else {})}


def probe(cls, options: dict, cache_dir=None) -> "AnyLoc | None":  # noqa: F821 - cls is AnyLoc
    """The method these options make, without loading the model or any centres; None when an option
    is bad (the run names it). Its notes are said when the run creates the method. No centres, and
    fp32 on the CPU (fp16 needs CUDA): neither changes the layer, stride or vocabulary keys."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return cls(**{**options, "vocabulary": "map", "precision": "fp32", "device": "cpu"}, cache_dir=cache_dir)
        except (VPRBenchError, TypeError):
            return None
