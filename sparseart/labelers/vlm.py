"""Optional VLM part labeler: ask a vision-language model which masks move together (off by default).

For up to ``max_pairs`` image pairs (start frame i, end frame i) it asks three questions, each a
template in ``prompts/`` with the JSON schema of its answer:

1. ``part_count``: how many parts moved (plain photos). Aggregated by mode over pairs; a tie goes
   to the larger count (a labelling may use fewer parts than asked, never more).
2. ``mask_labels``: for both photos of the pair at once, with numbered overlays of each image's own
   mask ids, a label per mask: 0 = not the object, 1 = static base, 2..n+1 = moving parts. Because
   one answer covers both photos, the model's part numbers link start and end *within* a pair.
3. ``joint_types``: revolute or prismatic (+ confidence) per moving part, on overlays coloured by
   the pair's part numbers.

Reconciling part numbers *across* pairs (rule): the pair whose labelling uses the most moving
parts (first on ties) is the reference. Every other pair's moving part k is matched to a reference
part by 3D overlap within each state (start with start, end with end; this holds posed or not, as
each state's frames share one frame): each of k's points votes for the reference part of the
nearest reference-labelled point within 3 point spacings; votes of both states are summed and
divided by the number of k's points that found a neighbour; the Hungarian algorithm maximises the
total, and a match needs a share >= ``min_match_share`` (else k's masks stay unassigned, with a
warning). Segments of frames outside the valid pairs (more views than pairs, a pair whose answers
were invalid) take the majority final label of their points' nearest labelled neighbours.

Joint type (decision): the mode over pairs of each part's type is always the ``type_prior``; it
becomes ``PartSpec.joint_type`` (the fitter then skips classification) only when every pair that
typed the part agrees (share >= ``type_agreement``) and their mean confidence >= ``type_confidence``.

Failure: no scene images or masks, a service failure (no server, timeout, HTTP error after
retries, an oversized or over-deep response) or no valid answer after ``answer_retries`` re-asks
-> the rule-based labeler runs instead and the result carries a warning naming the cause. Any
other exception on the VLM path (an answer shaped so that a check trips over it) falls back the
same way, its type named in the warning. Answers are cached per scene content,
so the pipeline's second call (unposed scenes: label, align, label again) sends no new requests.
"""
from __future__ import annotations

import hashlib
import json
import string
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from ..types import Frame, LabelledCloud, PartLabels, PartSpec, Scene
from .base import PartLabeler, labels_from_segment_maps
from .overlay import numbered_overlay, png_data_url
from .vlm_client import VlmAnswerError, VlmClient, VlmError

PROMPTS_DIR = Path(__file__).resolve().parents[2] / "prompts"
PLACEHOLDERS = {"part_count": {"max_parts", "schema"},
                "mask_labels": {"n_moving", "last_part", "start_ids", "end_ids", "schema"},
                "joint_types": {"parts", "labelling", "schema"}}
VOTE_SAMPLE = 3000          # points per part / segment that vote in 3D matching
REFERENCE_SAMPLE = 20000    # labelled reference points in a KD-tree
VOTE_RADIUS_SPACINGS = 3.0
NO_NEIGHBOUR = -2


@dataclass
class VlmLabelerConfig:
    """Tuning of :class:`VlmLabeler` (service settings are constructor arguments)."""

    max_pairs: int = 3
    max_parts: int = 10
    answer_retries: int = 1
    type_agreement: float = 1.0
    type_confidence: float = 0.7
    min_match_share: float = 0.3
    overlay_min_side: int = 384
    prompts_dir: Path = PROMPTS_DIR
    seed: int = 0


@dataclass
class _PairAnswer:
    """Validated answers for pair ``index`` (start frame index, end frame index)."""

    index: int
    labels: dict[str, dict[int, int]]                   # state -> mask id -> part number
    types: dict[int, tuple[str, float]] = field(default_factory=dict)  # part number -> (type, conf)

    @property
    def moving(self) -> list[int]:
        return sorted({p for table in self.labels.values() for p in table.values() if p >= 2})


class VlmLabeler:
    """Part labeler backed by an OpenAI-compatible VLM; see the module docstring.

    Args:
        base_url, model, api_key, timeout, max_retries, backoff: passed to
            :class:`~sparseart.labelers.vlm_client.VlmClient` (env fallbacks there).
        config: :class:`VlmLabelerConfig`.
        fallback: labeler used when the VLM fails (default ``RuleBasedLabeler()``).
        client: an already built client (overrides the service arguments).

    After each :meth:`label`, ``last_report`` holds: ``fallback`` (the cause, or None), ``counts``
    (part count answers), ``n_moving`` (their mode), ``problems`` (invalid answers), ``pairs``
    (pairs used), ``reference_pair``, ``renumbered`` ({pair: {model's number: reference number}})
    and ``n_parts``. It never holds the API key.

    Raises:
        ValueError: missing base URL / model, or a prompt file that is missing or not valid.
    """

    name = "vlm"

    def __init__(self, base_url: str | None = None, model: str | None = None, api_key: str | None = None,
                 *, timeout: float = 30.0, max_retries: int = 2, backoff: float = 0.5,
                 config: VlmLabelerConfig | None = None, fallback: PartLabeler | None = None,
                 client: VlmClient | None = None) -> None:
        self.config = config or VlmLabelerConfig()
        if self.config.max_pairs < 1 or not 0 <= self.config.max_parts <= 10:
            raise ValueError("VLM labeler: max_pairs must be >= 1 and max_parts in [0, 10]")
        self.client = client or VlmClient(base_url, model, api_key, timeout=timeout,
                                          max_retries=max_retries, backoff=backoff)
        self.prompts = {q: _load_prompt(Path(self.config.prompts_dir), q) for q in PLACEHOLDERS}
        self._fallback = fallback
        self._cache: tuple[str, tuple[list[_PairAnswer], dict[str, Any]] | VlmError] | None = None
        self.last_report: dict[str, Any] = {}

    def __repr__(self) -> str:
        return f"VlmLabeler({self.client!r})"

    def label(self, start: LabelledCloud, end: LabelledCloud, scene: Scene | None = None,
              aligned: bool = True, motion_hints: list[np.ndarray] | None = None,
              posed: bool | None = None) -> PartLabels:
        """Label parts from the VLM's answers, or from the fallback labeler with a warning.

        O(P) requests for P pairs (3 per pair, plus re-asks), then O(N log N) KD-tree voting."""
        self.last_report = {"fallback": None}
        try:
            lifted = set(np.unique(start.frame_index).tolist()) & set(np.unique(end.frame_index).tolist())
            answers, asked = self._answers(scene, lifted)
            self.last_report.update(asked)
            labels = _labels_from_answers(answers, start, end, self.config, self.last_report)
            if asked["problems"]:
                labels.warnings.append(f"VLM: {len(asked['problems'])} invalid answer(s) ignored or re-asked "
                                       f"(first: {self.client.redact(asked['problems'][0])})")
        except Exception as error:  # noqa: BLE001 - any failure of the VLM path falls back to the rules
            # VlmError: the service or its answers; anything else (a RecursionError, a TypeError
            # on an odd answer shape, a MemoryError) is reported with its type, never raised.
            detail = " ".join(str(error).split())[:200]
            cause = self.client.redact(detail if isinstance(error, VlmError)
                                       else f"{type(error).__name__}: {detail}" if detail else type(error).__name__)
            self.last_report["fallback"] = cause
            fallback = self._fallback
            if fallback is None:
                from .rules import RuleBasedLabeler

                fallback = RuleBasedLabeler()
            labels = fallback.label(start, end, scene, aligned=aligned, posed=posed)
            labels.warnings.insert(0, f"VLM labeler not used ({cause}); parts come from the "
                                      f"{fallback.name} labeler")
        return labels

    # ------------------------------------------------------------------ questions

    def _answers(self, scene: Scene | None, lifted: set[int]) -> tuple[list[_PairAnswer], dict[str, Any]]:
        """Validated answers of the first ``max_pairs`` pairs whose frames have masks and points in
        both clouds (``lifted`` frame indices), and a report (counts, problems); cached."""
        if scene is None:
            raise VlmError("no scene images (clouds were given directly)")
        usable = [i for i in range(min(len(scene.start), len(scene.end))) if i in lifted
                  and _mask_ids(scene.start[i]) and _mask_ids(scene.end[i])]
        pairs = [(i, scene.start[i], scene.end[i]) for i in usable[:self.config.max_pairs]]
        if not pairs:
            raise VlmError("the scene has no masks for the VLM to label")
        key = _content_key(pairs)
        if self._cache is not None and self._cache[0] == key:
            cached = self._cache[1]
            if isinstance(cached, VlmError):
                raise cached
            return cached
        try:
            result = self._ask_all(pairs)
        except VlmError as error:
            self._cache = (key, error)
            raise
        self._cache = (key, result)
        return result

    def _ask_all(self, pairs: list[tuple[int, Frame, Frame]]) -> tuple[list[_PairAnswer], dict[str, Any]]:
        config, report = self.config, {}
        counts, problems = [], []
        for index, start, end in pairs:
            answer = self._ask("part_count", [png_data_url(start.rgb), png_data_url(end.rgb)], problems,
                               max_parts=config.max_parts)
            if answer is not None and answer["moving_parts"] > config.max_parts:
                problems.append(f"pair {index}: {answer['moving_parts']} parts > max_parts")
            elif answer is not None:
                counts.append(int(answer["moving_parts"]))
        if not counts:
            raise VlmAnswerError(f"no valid part count answer: {problems[-1]}")
        tally = Counter(counts)
        n_moving = max(tally, key=lambda c: (tally[c], c))
        report.update(counts=counts, n_moving=n_moving)
        answers = []
        for index, start, end in pairs:
            ids = {"start": _mask_ids(start), "end": _mask_ids(end)}
            images = [self._mask_overlay(start, ids["start"]), self._mask_overlay(end, ids["end"])]
            answer = self._ask("mask_labels", images, problems, n_moving=n_moving, last_part=n_moving + 1,
                               start_ids=json.dumps(ids["start"]), end_ids=json.dumps(ids["end"]),
                               check=lambda a, ids=ids: _check_labelling(a, ids, n_moving))
            if answer is None:
                continue
            pair = _PairAnswer(index, _check_labelling(answer, ids, n_moving))
            if pair.moving:
                images = [self._part_overlay(start, pair.labels["start"], pair.moving),
                          self._part_overlay(end, pair.labels["end"], pair.moving)]
                typed = self._ask("joint_types", images, problems, parts=json.dumps(pair.moving),
                                  labelling=json.dumps(answer, sort_keys=True),
                                  check=lambda a, moving=pair.moving: _check_types(a, moving))
                pair.types = _check_types(typed, pair.moving) if typed is not None else {}
            answers.append(pair)
        report["problems"] = list(problems)
        if not answers:
            raise VlmAnswerError(f"no valid mask labelling answer: {problems[-1]}")
        return answers, report

    def _ask(self, question: str, images: list[str], problems: list[str], check=None,
             **fields: Any) -> dict[str, Any] | None:
        """One question, re-asked up to ``answer_retries`` times while the answer is invalid.
        Returns None when every answer was invalid (the problem is appended to ``problems``);
        a service failure propagates (no point asking the other pairs)."""
        template, schema = self.prompts[question]
        text = template.substitute(schema=json.dumps(schema), **fields)
        for _ in range(self.config.answer_retries + 1):
            try:
                answer = self.client.ask_json(text, images, schema)
                if check is not None:
                    check(answer)
                return answer
            except VlmAnswerError as error:
                cause = str(error)
            problems.append(f"{question}: {cause}")
        return None

    def _mask_overlay(self, frame: Frame, ids: list[int]) -> str:
        overlay = numbered_overlay(frame.rgb, frame.mask, ids, min_side=self.config.overlay_min_side)
        return png_data_url(overlay)

    def _part_overlay(self, frame: Frame, labels: dict[int, int], moving: list[int]) -> str:
        lut = np.zeros(int(frame.mask.max()) + 1, dtype=np.int64)
        for mask_id, part in labels.items():
            lut[mask_id] = part
        parts = lut[np.clip(frame.mask, 0, None)]
        overlay = numbered_overlay(frame.rgb, parts, moving, min_side=self.config.overlay_min_side, color_by="id")
        return png_data_url(overlay)


# ---------------------------------------------------------------------- answers -> parts


def _load_prompt(folder: Path, question: str) -> tuple[string.Template, dict[str, Any]]:
    text_path, schema_path = folder / f"{question}.txt", folder / f"{question}.schema.json"
    try:
        template = string.Template(text_path.read_text(encoding="utf-8"))
        schema = json.loads(schema_path.read_text(encoding="utf-8"))
    except OSError as error:
        raise ValueError(f"{error.filename}: cannot read VLM prompt file ({error.strerror})") from None
    except json.JSONDecodeError as error:
        raise ValueError(f"{schema_path}: not valid JSON ({error.msg}, line {error.lineno})") from None
    if not isinstance(schema, dict):
        raise ValueError(f"{schema_path}: a JSON schema must be an object")
    if not template.is_valid() or set(template.get_identifiers()) - PLACEHOLDERS[question]:
        raise ValueError(f"{text_path}: bad placeholder(s); allowed: "
                         f"{', '.join('$' + n for n in sorted(PLACEHOLDERS[question]))} and $$")
    return template, schema


def _mask_ids(frame: Frame) -> list[int]:
    if frame.mask is None:
        return []
    return [int(i) for i in np.unique(frame.mask) if i > 0]


def _content_key(pairs: list[tuple[int, Frame, Frame]]) -> str:
    digest = hashlib.sha1()
    for index, *frames in pairs:
        digest.update(str(index).encode())
        for frame in frames:
            digest.update(np.ascontiguousarray(frame.rgb).tobytes())
            digest.update(np.ascontiguousarray(frame.mask).tobytes())
    return digest.hexdigest()


def _check_labelling(answer: dict[str, Any], ids: dict[str, list[int]],
                     n_moving: int) -> dict[str, dict[int, int]]:
    """Semantic checks of a schema-valid mask labelling; returns state -> {mask id: part}."""
    labels: dict[str, dict[int, int]] = {}
    for state in ("start", "end"):
        table: dict[int, int] = {}
        for entry in answer[state]:
            mask, part = int(entry["mask"]), int(entry["part"])  # schema-checked integers (2.0 allowed)
            if mask not in ids[state]:
                raise VlmAnswerError(f"{state} mask {mask} is not in the image (masks: {ids[state]})")
            if mask in table:
                raise VlmAnswerError(f"{state} mask {mask} is labelled twice")
            if part > n_moving + 1:
                raise VlmAnswerError(f"{state} mask {mask}: part {part} > {n_moving + 1} "
                                     f"({n_moving} moving parts)")
            table[mask] = part
        missing = sorted(set(ids[state]) - set(table))
        if missing:
            raise VlmAnswerError(f"{state} masks {missing} are not labelled")
        labels[state] = table
    used = {p for table in labels.values() for p in table.values()}
    if 1 not in used:
        raise VlmAnswerError("no mask is labelled 1 (the static base)")
    moving = sorted(p for p in used if p >= 2)
    if moving != list(range(2, 2 + len(moving))):
        raise VlmAnswerError(f"moving part numbers {moving} are not contiguous from 2")
    return labels


def _check_types(answer: dict[str, Any], moving: list[int]) -> dict[int, tuple[str, float]]:
    types = {}
    for entry in answer["joints"]:
        part = int(entry["part"])
        if part in types:
            raise VlmAnswerError(f"joint type of part {part} given twice")
        types[part] = (entry["type"], float(entry["confidence"]))
    if sorted(types) != moving:
        raise VlmAnswerError(f"joint types given for parts {sorted(types)}, expected {moving}")
    return types


def _point_parts(cloud: LabelledCloud, frame_index: int, table: dict[int, int]) -> np.ndarray:
    """(N,) part number per point of ``cloud`` from one frame's mask labels; -1 elsewhere. O(N)."""
    mapping = {seg: table[mask] for seg, (frame, mask) in cloud.segment_source.items()
               if frame == frame_index and mask in table}
    return _map(cloud.segment, mapping)


def _map(keys_per_point: np.ndarray, mapping: dict[int, int]) -> np.ndarray:
    result = np.full(len(keys_per_point), -1, dtype=np.int64)
    if mapping:
        keys = np.array(sorted(mapping), dtype=np.int64)
        values = np.array([mapping[k] for k in keys], dtype=np.int64)
        slot = np.clip(np.searchsorted(keys, keys_per_point), 0, len(keys) - 1)
        hit = keys[slot] == keys_per_point
        result[hit] = values[slot[hit]]
    return result


def _spacing(points: np.ndarray, rng: np.random.Generator) -> float:
    sample = points[rng.choice(len(points), min(len(points), 2000), replace=False)]
    distances, _ = cKDTree(sample).query(sample, k=2)
    return float(max(np.median(distances[:, 1]), 1e-9))


def _votes(query: np.ndarray, reference: np.ndarray, reference_labels: np.ndarray, radius: float,
           rng: np.random.Generator) -> np.ndarray:
    """Label of the nearest reference point within ``radius`` for a sample of <= VOTE_SAMPLE query
    points; ``NO_NEIGHBOUR`` where there is none. O((Q + R) log R)."""
    if len(reference) == 0 or len(query) == 0:
        return np.empty(0, dtype=np.int64)
    keep = rng.choice(len(reference), min(len(reference), REFERENCE_SAMPLE), replace=False)
    sample = query[rng.choice(len(query), min(len(query), VOTE_SAMPLE), replace=False)]
    distances, nearest = cKDTree(reference[keep]).query(sample, distance_upper_bound=radius)
    found = np.isfinite(distances)
    votes = np.full(len(sample), NO_NEIGHBOUR, dtype=np.int64)
    votes[found] = reference_labels[keep][nearest[found]]
    return votes


def _labels_from_answers(answers: list[_PairAnswer], start: LabelledCloud, end: LabelledCloud,
                         config: VlmLabelerConfig, report: dict[str, Any]) -> PartLabels:
    """Reconcile the pairs' part numbers (module docstring rule) and build :class:`PartLabels`."""
    rng = np.random.default_rng(config.seed)
    clouds = {"start": start, "end": end}
    radius = {s: VOTE_RADIUS_SPACINGS * _spacing(c.points, rng) for s, c in clouds.items() if len(c) >= 2}
    if len(radius) < 2:
        raise VlmError("too few points to match the VLM's labels in 3D")
    point_parts = {(p.index, s): _point_parts(clouds[s], p.index, p.labels[s]) for p in answers for s in clouds}
    reference = max(answers, key=lambda p: (len(p.moving), -p.index))
    warnings: list[str] = []
    renumber: dict[int, dict[int, int]] = {}   # pair index -> model part number -> final part id
    for pair in answers:
        table = {0: -1, 1: 0}
        if pair is reference:
            table.update({k: k - 1 for k in pair.moving})
        elif pair.moving:
            share = np.zeros((len(pair.moving), len(reference.moving)))
            found = np.zeros(len(pair.moving))
            for state, cloud in clouds.items():
                ref_parts = point_parts[(reference.index, state)]
                ref_moving = ref_parts >= 2
                for row, k in enumerate(pair.moving):
                    votes = _votes(cloud.points[point_parts[(pair.index, state)] == k],
                                   cloud.points[ref_moving], ref_parts[ref_moving], radius[state], rng)
                    found[row] += np.count_nonzero(votes != NO_NEIGHBOUR)
                    for col, j in enumerate(reference.moving):
                        share[row, col] += np.count_nonzero(votes == j)
            share /= np.maximum(found, 1.0)[:, None]
            rows, cols = linear_sum_assignment(-share)
            for row, col in zip(rows, cols):
                if share[row, col] >= config.min_match_share:
                    table[pair.moving[row]] = reference.moving[col] - 1
            lost = [k for k in pair.moving if k not in table]
            if lost:
                warnings.append(f"VLM pair {pair.index}: part(s) {lost} overlap no part of reference pair "
                                f"{reference.index} in 3D; their masks are left unassigned")
            if any(table[k] != k - 1 for k in pair.moving if k in table):
                renumbered = {k: table[k] + 1 for k in pair.moving if k in table}
                report.setdefault("renumbered", {})[pair.index] = renumbered
        renumber[pair.index] = table
    maps = {}
    for state, cloud in clouds.items():
        mapping: dict[int, int] = {}
        for pair in answers:
            for segment, (frame, mask) in cloud.segment_source.items():
                if frame == pair.index and mask in pair.labels[state]:
                    part = renumber[pair.index].get(pair.labels[state][mask], -1)
                    if part >= 0:
                        mapping[segment] = part
        _label_other_frames(cloud, mapping, {p.index for p in answers}, radius[state], rng)
        maps[state] = mapping
    n_parts = len(reference.moving)
    parts = [PartSpec(id=0, role="static")]
    type_prior: dict[int, str] = {}
    for part_id in range(1, n_parts + 1):
        votes = [pair.types[k] for pair in answers for k, final in renumber[pair.index].items()
                 if final == part_id and k in pair.types]
        joint_type = None
        if votes:
            tally = Counter(t for t, _ in votes)
            mode, hits = max(tally.items(), key=lambda item: (item[1], item[0] == "revolute"))
            confidence = float(np.mean([c for t, c in votes if t == mode]))
            type_prior[part_id] = mode
            if hits / len(votes) >= config.type_agreement and confidence >= config.type_confidence:
                joint_type = mode
            else:
                warnings.append(f"VLM joint type of part {part_id} is only a prior ({mode}: {hits}/{len(votes)} "
                                f"pairs, confidence {confidence:.2f})")
        parts.append(PartSpec(id=part_id, role="movable", joint_type=joint_type, parent=0))
    labels = labels_from_segment_maps(parts, start, end, maps["start"], maps["end"])
    if not (np.any(labels.start_part >= 0) and np.any(labels.end_part >= 0)):
        raise VlmError("the VLM's labels cover no point of one state (masks without valid depth?)")
    labels.type_prior = type_prior
    labels.warnings.extend(warnings)
    report.update(reference_pair=reference.index, pairs=[p.index for p in answers], n_parts=n_parts)
    return labels


def _label_other_frames(cloud: LabelledCloud, mapping: dict[int, int], labelled_frames: set[int],
                        radius: float, rng: np.random.Generator) -> None:
    """Give segments of frames the VLM did not label the majority part of their points' nearest
    labelled neighbours (within ``radius``); in place on ``mapping``. O(S · sample · log N)."""
    others = [seg for seg, (frame, _) in cloud.segment_source.items() if frame not in labelled_frames]
    if not others:
        return
    point_part = _map(cloud.segment, mapping)   # -1: labelled "not the object"
    labelled = np.isin(cloud.frame_index, list(labelled_frames)) & (cloud.segment >= 0)
    for segment in others:
        votes = _votes(cloud.points[cloud.segment == segment], cloud.points[labelled], point_part[labelled],
                       radius, rng)
        votes = votes[votes != NO_NEIGHBOUR]
        if len(votes):
            values, counts = np.unique(votes, return_counts=True)
            best = int(np.argmax(counts))
            if values[best] >= 0 and counts[best] >= 0.5 * len(votes):
                mapping[segment] = int(values[best])
