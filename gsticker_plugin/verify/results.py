"""The report of ``ns-verify-owner``, typed: what ``report.json`` holds, per key and per view.

Each class is the schema of one JSON object of the report (a ``TypedDict``, so the report is written as it is built
and type-checked where it is read). Fields marked ``NotRequired`` appear only for some decoders or inputs.

Examples:
    >>> t: Thresholds = {"theoretical": 40, "empirical": None, "used": 40, "per_view_fpr_target": 1e-6,
    ...                  "per_view_fpr_at_used": 2.0e-7}
    >>> t["used"]
    40
"""

from __future__ import annotations

from typing import Any, Dict, List, NotRequired, Optional, TypedDict


class Thresholds(TypedDict):
    """Per-view match thresholds: from the binomial null (``theoretical``), from the key's measured null
    (``empirical``, None without one), the stricter one ``used``, and the per-view false-positive rates."""

    theoretical: int
    empirical: Optional[int]
    used: int
    per_view_fpr_target: float
    per_view_fpr_at_used: float


class NullSummary(TypedDict):
    """A key's stored empirical null for one decoder: its match counts' statistics and the threshold it implies."""

    n: int
    mean_matches: float
    sd_matches: float
    max_matches: int
    chance_mean: float
    chance_sd: float
    threshold: int
    sources: List[str]
    created: Optional[float]
    meaning: str
    exceed_at_used_threshold: NotRequired[int]
    exceed_upper95_at_used_threshold: NotRequired[float]


class ViewResult(TypedDict):
    """One view's reading with one key; ``geometry`` / ``image_fit``: the informed decoder's diagnostics."""

    name: str
    matches: int
    num_bits: int
    bit_accuracy: float
    pvalue: float
    score: Optional[float]
    passed: bool
    decoded: str
    note: NotRequired[str]
    geometry: NotRequired[Dict[str, Any]]
    image_fit: NotRequired[Dict[str, Any]]


class BaseRun(TypedDict):
    """The owner's unwatermarked base run an informed decoder read against."""

    config: str
    checkpoint: str
    method: str


class KeyResult(TypedDict):
    """One key's result: thresholds, the view vote, the verdict, and every view."""

    key: str
    owner_id: str
    num_bits: int
    verdict: str
    owned: bool
    thresholds: Thresholds
    views: int
    views_passing: int
    share_passing: float
    views_needed: int
    min_share: float
    model_fpr_bound: float
    model_pvalue: float
    vote_statistic: float
    matches_min: int
    matches_median: int
    matches_max: int
    mean_bit_accuracy: float
    mean_score: Optional[float]
    decoder: str
    mark: str
    null_exact: bool
    null_caveats: List[str]
    message_source: str
    empirical_null: Optional[NullSummary]
    per_view: List[ViewResult]
    null_note: NotRequired[str]
    base: NotRequired[BaseRun]
    scene_agreement: NotRequired[Optional[float]]
    soft_score_pvalue: NotRequired[float]
    adjusted_pvalue: NotRequired[float]


class DecoderInfo(TypedDict):
    """The decoder that read the views: ``kind`` (geometry, image, extractor), whether it is ``informed``, what it
    does, and its notes; informed decoders add the base runs they read against."""

    kind: str
    informed: bool
    description: str
    notes: List[str]
    bases: NotRequired[List[str]]
    signals: NotRequired[List[List[str]]]
    cameras: NotRequired[str]


class InputInfo(TypedDict):
    """What was read: a model or a folder of images, its views and what was skipped (with the reason)."""

    kind: str
    source: str
    views: int
    skipped: List[Dict[str, Any]]
    details: Dict[str, Any]


class Settings(TypedDict):
    """The statistical and sampling settings of the run."""

    fpr: float
    min_share: float
    attack: str
    num_views: Optional[int]
    seed: int
    correction: Optional[str]


class MultipleTesting(TypedDict):
    """Several keys: the correction applied and the family-wise false-positive rate."""

    keys: int
    correction: str
    family_wise_fpr: float
    rule: str


class Commitment(TypedDict):
    """``--commitment`` / ``--public-key`` checked against the key."""

    key: str
    matches: bool
    given: NotRequired[str]
    meaning: NotRequired[str]
    public_key: NotRequired[str]
    signed: NotRequired[bool]


class Report(TypedDict):
    """``report.json``."""

    tool: str
    created: float
    input: InputInfo
    settings: Settings
    decoder: DecoderInfo
    commitment: Optional[Commitment]
    keys: List[KeyResult]
    multiple_testing: Optional[MultipleTesting]
    verdict: str
    owned_by: List[str]
    exit_status: int
    files: NotRequired[List[str]]
