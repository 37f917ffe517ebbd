"""Whether to trust a registration: a verdict, ``registered``, ``doubtful`` or ``failed``, with its reasons.

A wrong pose can score like a right one: a vertebra shifted by one level, or a pelvis turned
10 deg and moved 25 mm in a small field, keeps a gradient NCC of 0.86-0.89 while a right pose on
a linear display scores 0.29. The similarity alone cannot tell them apart, so the verdict weighs
independent evidence, each gathered once after the registration (:func:`gather_evidence`):

* ``similarity``: the final similarity (the registration's own score, 1 = identical edges);
* ``tone_fit``: the NCC of the X-ray's intensities (its toned version for a display image) with
  the line DRR at the final pose over the field: the intensities agree where the pose is right,
  whatever the edges do (0th order where the similarity is 1st);
* ``runner_up``: the best refined start of the global search that ended at a distinct pose
  (:data:`DISTINCT_DEG` / :data:`DISTINCT_MM` away): two poses that score alike mean the X-ray
  does not decide between them. Where the search's grid did not run, no distinct alternative
  was examined: the checks below (the local similarity, the depth profile, the rival) judge such
  a pose; a method without the search (no refinement of the network's pose in a box wide in
  depth) needs a clear match too (``sure_similarity``);
* ``local_similarity``: the gradient NCC window by window
  (:func:`register.engines.metrics.local_gradient_ncc`: patch gradient NCC, Grupp et al. 2020, in
  15 px windows at the optimiser's 128 px) of the X-ray with the line DRR at the final pose: whether
  the edges agree window by window over the field (None: a field smaller than one window). The whole image's correlation can rest on one strong
  edge: where a linear display shows the body as a flat white and the air beside it black, the
  body's outline is the only edge, and any pose that puts the DRR's outline there scores 0.93
  (a frame 153 mm off in depth, every other check passed); window by window, its bone edges meet
  nothing (0.20 there, 0.63 at the truth);
* ``network_gap``: how far the network's own pose is from the final one (deg, mm): recorded, not
  judged (a network on a patient it never saw is often far off where the search found the pose);
* ``field_fraction``: the share of the X-ray's pixels the registration used;
* ``depth_drop``: how much the similarity falls when the pose moves :data:`DEPTH_PROBE_MM` along
  the ray through the anatomy centre, nearer or farther (the image scaled about the centre's
  projection): a single view reads depth from the magnification alone, and where the similarity
  barely changes over +-30 mm the depth is not determined (most wrong registrations of known
  truth were off in depth: 14-170 mm);
* ``depth_profile``: the same probe with the other five parameters fitted again at each depth
  (:func:`depth_profile`): a wrong depth is often held by a tilt that makes up for the
  magnification, which the plain probe does not try, so its drop stays large where the
  profile's vanishes;
* ``rival``: the best pose near the final one by edges and intensities together (:func:`rival`:
  the similarity plus the tone fit, maximised from the final pose): a right pose is near the best
  of both, so a distinct pose that scores clearly more on the two together says the registration
  stopped short of where the X-ray puts the anatomy;
* the runner-up's joint margin: the final pose's similarity plus tone fit against the runner-up's
  (``runner_up``'s ``tone_fit``): a distinct start of the search that scores as much on the two
  together is as good an answer.

The depth profile and the rival need a CMA-ES (``judge_result``'s ``refine`` and ``rival_search``); where they were
not gathered (``judge_result`` without them), their checks are left out.

:func:`judge` turns the evidence into the verdict with :class:`VerdictSettings`, whose thresholds
were calibrated on registrations of known truth (``benchmarks/verdict.py``; docs/results.md,
"Whether to trust a registration"). ``ctxreg register`` prints it as its last line and exits with
:data:`EXIT_STATUS` (0 registered, 3 otherwise) after writing every output.

Example::

    >>> s = VerdictSettings()
    >>> judge({"similarity": 0.05, "tone_fit": 0.1, "runner_up": None, "search": "ran",
    ...        "field_fraction": 0.5}, s).label
    'failed'
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from register.engines.cmaes import CMAESRegistration, along_view_ray
from register.engines.metrics import NoWindowError, bind_metric, bind_metric_at, local_gradient_ncc, ncc
from register.engines.result import RegistrationError
from register.engines.search import GlobalSearchSettings
from sim.projection.geometry import pose_from_params
from sim.projection.se3 import rotation_error_deg

__all__ = ["Verdict", "VerdictSettings", "gather_evidence", "checks", "failure", "judge", "judge_result", "pose_gap", "runner_up",
           "depth_probe_poses", "depth_profile", "rival", "DEPTH_PROBE_MM", "EXIT_STATUS",
           "LABELS", "DISTINCT_DEG", "DISTINCT_MM", "DISTINCT_DEPTH_MM", "RIVAL_DISTINCT_DEPTH_MM", "CALIBRATED",
           "DECISION_MARGIN", "clearly_registered"]

#: The verdicts, best first.
LABELS = ("registered", "doubtful", "failed")

#: ``ctxreg register``'s exit status by verdict (after every output is written): a script keeps
#: the poses that exit 0.
EXIT_STATUS = {"registered": 0, "doubtful": 3, "failed": 3}

#: Two poses are distinct (another answer, not the same one refined differently) when their
#: rotations differ by more than this (deg), their anatomy centres by more than
#: :data:`DISTINCT_MM` (mm) across the view, or by more than :data:`DISTINCT_DEPTH_MM` (mm) along
#: it: at 100 mm from the centre, 4 deg moves a point 7 mm. A single view sees depth through the
#: magnification alone (20 mm at 700 mm from the source moves a point 100 mm off the centre by
#: 3 mm in the image), so the refined starts of a right registration often differ by 10-20 mm
#: in depth alone with similarities within 0.05 (benchmarks/verdict.py); counted as distinct, they
#: made 27 % of right registrations doubtful where 20 mm made 13 % so, with no false accept either way.
DISTINCT_DEG = 4.0
DISTINCT_MM = 10.0
DISTINCT_DEPTH_MM = 20.0

#: The rival (:func:`rival`) is another answer where it is :func:`distinct` or this far (mm) from the
#: final pose in depth alone: a pose that edges and intensities together favour clearly (more than
#: ``max_rival_gain``) 10 mm nearer or farther says the X-ray puts the anatomy a right registration's
#: bar (10 mm) away along the ray. (The runner-up's :data:`DISTINCT_DEPTH_MM`, 20 mm, is for starts of
#: the search that score alike, which right registrations' do 10-20 mm apart in depth; a rival scores
#: more.) A frame of instrumented surgery 12.2 mm off, mostly in depth, had a rival 13 mm deeper
#: scoring 0.034 more, and was called registered with 20 mm (``studies/heldout6.toml``,
#: docs/results.md); of the 409 registrations of the verdict's tables (``benchmarks/verdict_rows/``)
#: it changes no other verdict, nor any of the 128 with ``--tools detect`` there.
RIVAL_DISTINCT_DEPTH_MM = 10.0

#: The margin (a share of each calibrated threshold's value) a decision must clear that rests on
#: one pose's evidence alone: the calibration demands it of wrong poses (each still rejected with
#: every threshold this much looser, ``benchmarks/verdict.py``), :func:`clearly_registered` of a
#: pose kept without the grid (every threshold this much stricter).
DECISION_MARGIN = 0.1

#: How far (mm) along the ray through the anatomy centre the depth probe moves the final pose, each
#: way (:func:`depth_probe_poses`): 30 mm at 700 mm from the source scales the image by 4 %.
DEPTH_PROBE_MM = 30.0

#: The depth profile (:func:`depth_profile`): the CMA-ES generations of the fit at each probe's
#: depth, and the half-width (mm) of the box that pins the depth there.
PROFILE_GENERATIONS = 25
PROFILE_PIN_MM = 0.5

#: The rival (:func:`rival`): the half-width (mm) of its box in depth (in plane, the refinement's
#: box) and its CMA-ES generations.
RIVAL_DEPTH_MM = 90.0
RIVAL_GENERATIONS = 30


@dataclass(frozen=True)
class VerdictSettings:
    """The thresholds of :func:`judge`. ``min_similarity``, ``min_tone_fit``, ``min_margin``,
    ``min_joint_margin``, ``sure_similarity``, ``min_depth_drop``, ``min_profile_drop``,
    ``max_rival_gain`` and ``min_local_similarity`` are ``benchmarks/verdict.py --calibrate``'s choice
    on 120 registrations of known truth (the training pelvis, six conditions, the default pipeline
    and the grid always; ``benchmarks/verdict_rows/calib.jsonl``): no false accept, and every
    registration 15 mm off or more still rejected with each threshold 10 % looser (no threshold
    rests on the exact value of a wrong pose's evidence); of those, the most right registrations
    accepted, ties to the stricter. Three checks decide calibration rows alone: the similarity (a
    frame 24.6 mm off at 0.25), the tone fit (one 10.2 mm off at 0.56) and the depth profile (one
    30.8 mm off whose profile drops 0.012); the runner-up margins, the depth probe, the rival and
    the local similarity decided none alone (the strictest of the grid's values that keep the same
    rows was kept: the local similarity's 0.35, where the pipeline searches a pose again; it is
    there for the held-out frame whose outline was its only edge, module doc). ``fail_below``,
    ``tone_fail_below`` and ``min_field_fraction`` are floors no right registration came near.

    Attributes:
        fail_below: a final similarity below this is ``failed`` (the DRR does not match the X-ray).
        tone_fail_below: a tone fit below this is ``failed`` (the intensities disagree: a wrong
            pose, or an X-ray of other anatomy).
        min_similarity: ``registered`` needs at least this similarity.
        min_tone_fit: ``registered`` needs at least this tone fit.
        min_margin: ``registered`` needs the final similarity to beat a distinct runner-up by at
            least this much.
        sure_similarity: where the method has no global search (evidence ``search`` ``"none"``: the
            network alone, CMA-ES alone), ``registered`` needs at least this similarity; None: not
            judged. No calibration row is of such a method, and the calibration keeps the strictest
            value it tries (the pipeline's ``refined_above``): the network's pose unrefined, 10.9
            mm off, scored 0.84 and passed every other check. A pose of contextual+cmaes registered
            without the grid (``"skipped"``; ``"off"``, ``--search off``: refined in a box +-90 mm
            in depth) is judged by the other checks, without a floor: on the calibration pelvis's 40
            no-grid registrations (``benchmarks/verdict_rows/calib_off.jsonl``) they registered 17
            of 19 right ones and none of the 21 wrong ones, where a floor of 0.88 registered 6.
        min_field_fraction: ``registered`` needs at least this share of the X-ray's pixels used.
        min_depth_drop: ``registered`` needs the similarity to fall by at least this much
            :data:`DEPTH_PROBE_MM` nearer or farther (the better of the two).
        min_profile_drop: ``registered`` needs the depth profile (:func:`depth_profile`) to fall
            by at least this much; None: not judged.
        max_rival_gain: ``registered`` needs the rival (:func:`rival`), where another answer
            (:func:`distinct` from the final pose, or :data:`RIVAL_DISTINCT_DEPTH_MM` away in depth),
            to score at most this much more on the similarity and the tone fit together; None: not
            judged.
        min_joint_margin: ``registered`` needs the final pose's similarity plus tone fit to beat
            the runner-up's by at least this much (negative: the runner-up may score up to that
            much more); None: not judged.
        min_local_similarity: ``registered`` needs the local similarity (``local_similarity``, the
            patch gradient NCC at the final pose) to be at least this; None: not judged. The
            default pipeline searches a pose below it again by local similarity
            (:attr:`register.engines.search.GlobalSearchSettings.local_below`, whose value it takes:
            one number for both).
    """

    fail_below: float = 0.15
    tone_fail_below: float = 0.0
    min_similarity: float = 0.4
    min_tone_fit: float = 0.6
    min_margin: float = 0.02
    sure_similarity: float | None = GlobalSearchSettings.refined_above
    min_field_fraction: float = 0.1
    min_depth_drop: float = 0.05
    min_profile_drop: float | None = 0.02
    max_rival_gain: float | None = 0.03
    min_joint_margin: float | None = 0.02
    min_local_similarity: float | None = GlobalSearchSettings.local_below

    def __post_init__(self) -> None:
        for name, v in asdict(self).items():
            if v is None and name in ("sure_similarity", "min_profile_drop", "max_rival_gain", "min_joint_margin",
                                      "min_local_similarity"):
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or not -1 <= v <= 1:
                raise RegistrationError(f"VerdictSettings.{name} must be a number in [-1, 1], got {v!r}")

    def stricter(self, margin: float = DECISION_MARGIN) -> "VerdictSettings":
        """These settings with every calibrated threshold (:data:`CALIBRATED`) ``margin`` of its
        value stricter: lower bounds raised, ``max_rival_gain`` lowered; None stays None.

        Example::

            >>> VerdictSettings().stricter(0.1).min_local_similarity
            0.385
        """
        if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not 0 <= margin < 1:
            raise RegistrationError(f"stricter: margin must be a share in [0, 1), got {margin!r}")
        values = asdict(self)
        return replace(self, **{name: None if values[name] is None else round(
            values[name] + (-margin if name == "max_rival_gain" else margin) * abs(values[name]), 12)
            for name in CALIBRATED})


#: The thresholds of :class:`VerdictSettings` that ``benchmarks/verdict.py --calibrate`` chooses (the
#: floors ``fail_below``, ``tone_fail_below`` and ``min_field_fraction`` are not calibrated).
CALIBRATED = ("min_similarity", "min_tone_fit", "min_margin", "min_joint_margin", "sure_similarity",
              "min_depth_drop", "min_profile_drop", "max_rival_gain", "min_local_similarity")


def clearly_registered(verdict: "Verdict", margin: float = DECISION_MARGIN) -> bool:
    """Whether ``verdict``'s evidence is ``registered`` with every calibrated threshold ``margin``
    stricter (:meth:`VerdictSettings.stricter`): a decision taken on one pose alone, with no
    alternative examined (the pipeline keeping the network's pose without the grid,
    :meth:`register.engines.pipeline.ContextualPipeline.trusted`), must not rest on the exact value
    of its evidence. A pose of a held-out display 14.5 mm off passed the local similarity by 0.004
    (0.354 against 0.35) where the grid found the right one (docs/results.md, "Where the grid did not
    run")."""
    return verdict.label == "registered" and judge(verdict.evidence, VerdictSettings().stricter(margin)).label == "registered"


@dataclass(frozen=True)
class Verdict:
    """A registration's verdict: ``label`` (one of :data:`LABELS`), ``reasons`` (one sentence each:
    what decided it, and for ``registered`` what was checked) and the ``evidence`` it weighed
    (:func:`gather_evidence`)."""

    label: str
    reasons: tuple[str, ...]
    evidence: dict = field(default_factory=dict)

    @property
    def exit_status(self) -> int:
        return EXIT_STATUS[self.label]

    def line(self) -> str:
        """The verdict in one line, as ``ctxreg register`` prints it last."""
        return f"verdict: {self.label} ({'; '.join(self.reasons)})"

    def to_dict(self) -> dict:
        return {"verdict": self.label, "verdict_reasons": list(self.reasons), "verdict_evidence": self.evidence}


def pose_gap(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float, float]:
    """``(deg, mm, depth_mm)``: the rotation angle between two poses ``(4, 4)`` and how far apart
    they put the anatomy centre (their translations: ``X_cam = R (X - c) + t``), across the view
    (camera x, y) and along it (camera z, the depth)."""
    d = np.asarray(T_a, float)[:3, 3] - np.asarray(T_b, float)[:3, 3]
    return float(rotation_error_deg(T_a, T_b)), float(np.hypot(d[0], d[1])), float(abs(d[2]))


def depth_probe_poses(T: np.ndarray, d_mm: float = DEPTH_PROBE_MM) -> np.ndarray:
    """``(3, 4, 4)``: the pose ``T`` ``(4, 4)``, then moved ``d_mm`` farther from and nearer to the
    source along the ray through the anatomy centre (its translation scaled: ``X_cam = R (X - c)
    + t``, the centre's projection kept)."""
    T = np.asarray(T, float)
    out = np.repeat(T[None], 3, axis=0)
    depth = T[2, 3]
    for i, d in ((1, d_mm), (2, -d_mm)):
        out[i, :3, 3] = T[:3, 3] * (depth + d) / depth
    return out


def depth_profile(refine: CMAESRegistration, image: np.ndarray, params, *, mask: np.ndarray | None = None,
                  d_mm: float = DEPTH_PROBE_MM) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity ``d_mm`` farther from and nearer to the source along the ray through the
    anatomy centre, the other five parameters fitted again there.

    The plain probe (:func:`depth_probe_poses`) keeps the rotation and the in-plane translation,
    so a pose whose depth is wrong and whose tilt makes up for the magnification still shows a
    sharp drop there (a frame 45 mm off in depth and 5 deg in tilt: the plain probe fell by 0.26,
    the profile by 0.07; the right poses of its condition fell by 0.09-0.25 in the profile). Here
    CMA-ES (``refine``'s settings, :data:`PROFILE_GENERATIONS` generations, no polish, the depth
    pinned within :data:`PROFILE_PIN_MM`) starts at each moved pose (:func:`along_view_ray`).

    Args:
        refine: the registration's refinement (:class:`register.engines.cmaes.CMAESRegistration`
            at the image's size), scoring as the registration did.
        image: ``(h, w)`` the X-ray as registered; mask: ``(h, w)`` its valid pixels (None: all).
        params: ``(6,)`` the final pose (deg, mm).

    Returns ``(here, scores, poses)``: the similarity at ``params``, ``(2,)`` the best at the two
    depths (farther, nearer; the fit's or the moved pose's own, whichever is higher; all at full
    resolution, ``refine``'s finest metric; a moved pose that shows no CT is not fitted) and
    ``(2, 6)`` where they were found.
    """
    p = np.asarray(params, float).reshape(6)
    pinned = refine.adjusted(range_depth_mm=PROFILE_PIN_MM, sigma_depth_mm=PROFILE_PIN_MM,
                             generations=(PROFILE_GENERATIONS,), polish=False)
    s = pinned.settings
    score = bind_metric(s.per_level("metrics", len(s.levels) - 1), image, mask)
    here = float(score(pinned.render(p[None]))[0])
    probes = along_view_ray(p, [d_mm, -d_mm], pinned.geometry.sod_mm)
    plain = score(pinned.render(probes))  # CMA-ES fits at its level's resolution: the probe itself may score higher
    scores, poses = plain.copy(), probes.copy()
    seen = np.flatnonzero(pinned.in_view(probes))  # a probe that shows no CT is not fitted (CMA-ES cannot start there)
    for k, r in zip(seen, pinned.register_many(image, probes[seen], mask=mask, polish=False)):
        if r.similarity > scores[k]:
            scores[k], poses[k] = r.similarity, r.params
    return here, scores, poses


def rival(search: CMAESRegistration, image: np.ndarray, params, *, toned: np.ndarray | None = None,
          mask: np.ndarray | None = None, edge_metric: str | None = None) -> dict | None:
    """The best pose near the final one ``params`` ``(6,)`` (deg, mm) by edges and intensities
    together: CMA-ES on the similarity plus the tone fit of line DRRs (the similarity as the
    refinement scores the X-ray: tone-tolerant gradient NCC of ``image`` for a display image, with
    a ``toned`` version, else gradient NCC; the tone fit: the NCC of ``toned``, else ``image``), in
    ``search``'s box widened to +-:data:`RIVAL_DEPTH_MM` in depth (:data:`RIVAL_GENERATIONS`
    generations at its level, no polish).

    Either score alone has rivals at right poses: the edges of a display image favour a pose a
    degree or two off where its tone curve bends, and the intensities alone, shaped by scatter
    and the heel effect that line DRRs lack, favour poses 5-11 deg away that fit them 0.05-0.17
    better (benchmarks/verdict.py). Together they are near their best at a right pose (197 right
    registrations of realistic frames, nine display chains, two pelves: the rival gained 0-0.04, never
    at a distinct pose), and a wrong pose held by its edges alone sits beside one the two together
    favour (a frame 48 mm off: 0.15 more, 22 mm away in depth).

    Args:
        search: a line-DRR :class:`register.engines.cmaes.CMAESRegistration` at the image's size
            (its settings' box, level and population; its metric is not used).
        image: ``(h, w)`` the X-ray as registered; toned: its toned version (a display image; None:
            line integrals); mask: ``(h, w)`` its valid pixels (None: all).
        edge_metric: the similarity's name (:data:`register.engines.metrics.METRICS`); None: as the
            refinement scores the X-ray (above).

    Returns ``{"similarity", "tone_fit", "gain", "deg", "mm", "depth_mm"}``: the rival's two scores
    at full resolution, how much more their sum is than the final pose's, and its :func:`pose_gap`
    from the final pose (the final pose itself, gain 0, where the search ended no higher); None
    where the final pose shows no CT.
    """
    s = search.adjusted(range_depth_mm=RIVAL_DEPTH_MM, generations=(RIVAL_GENERATIONS,), polish=False)
    p = np.asarray(params, float).reshape(6)
    if not s.in_view(p)[0]:  # no CT in the view: nothing to fit (the similarity fails such a pose)
        return None
    edge_metric = edge_metric or ("gncc" if toned is None else "tone_tolerant_gncc")
    tones = image if toned is None else toned

    def scores(factor: int):
        return bind_metric_at(edge_metric, image, mask, factor), bind_metric_at("ncc", tones, mask, factor)

    def joint(factor: int):
        edges, fit = scores(factor)
        return lambda drrs: edges(drrs) + fit(drrs)

    edges, fit = scores(1)
    drrs = s.render(p[None])
    here_edges, here_tone = float(edges(drrs)[0]), float(fit(drrs)[0])
    found = s.maximise(joint, p)
    if found.similarity <= here_edges + here_tone:  # CMA-ES fits at its level's resolution: the final pose may be best
        return {"similarity": here_edges, "tone_fit": here_tone, "gain": 0.0, "deg": 0.0, "mm": 0.0, "depth_mm": 0.0}
    drrs = s.render(found.params[None])
    gap = pose_gap(found.pose, pose_from_params(p, s.geometry.sod_mm))
    return {"similarity": float(edges(drrs)[0]), "tone_fit": float(fit(drrs)[0]),
            "gain": float(found.similarity - here_edges - here_tone),
            "deg": round(gap[0], 3), "mm": round(gap[1], 3), "depth_mm": round(gap[2], 3)}


def distinct(gap: tuple[float, float, float]) -> bool:
    """Whether a pose gap ``(deg, mm, depth_mm)`` is another answer (:data:`DISTINCT_DEG`,
    :data:`DISTINCT_MM`, :data:`DISTINCT_DEPTH_MM`)."""
    return gap[0] > DISTINCT_DEG or gap[1] > DISTINCT_MM or gap[2] > DISTINCT_DEPTH_MM


def gather_evidence(*, similarity: float, pose: np.ndarray, image: np.ndarray, mask: np.ndarray | None,
                    drr: np.ndarray, toned: np.ndarray | None, search: dict | None, search_ran: bool,
                    network_pose: np.ndarray | None, sod_mm: float, field_fraction: float,
                    depth_scores=None, profile=None, rival_pose: dict | None = None, refined_tones=None,
                    search_off: bool = False) -> dict:
    """The evidence of the module doc, as plain numbers (JSON).

    Args:
        similarity: the final similarity. pose: ``(4, 4)`` the final pose.
        image / toned / mask: ``(h, w)`` the prepared X-ray, its toned version (None: not a display
            image) and its valid pixels (None: all). drr: ``(h, w)`` the line DRR at ``pose``.
        search: the global search's record (None: no search); search_ran: whether its grid ran;
            search_off: the pose is contextual+cmaes's without its search (``--search off``: the
            network's pose refined in a box wide in depth), evidence ``search`` ``"off"``, not
            ``"none"`` (a method without the search).
        network_pose: ``(4, 4)`` where the network's iteration ended (None: no network).
        sod_mm: the geometry's source-object distance (mm): the refined starts' poses from their parameters.
        field_fraction: the share of the X-ray's pixels in the registration's field.
        depth_scores: ``(3,)`` the similarity at :func:`depth_probe_poses` (None: not probed).
        profile: :func:`depth_profile`'s ``(here, scores, poses)`` (None: not profiled).
        rival_pose: :func:`rival`'s answer (None: not searched).
        refined_tones: ``(K,)`` the tone fit at each of the search's refined starts (None: not
            rendered): the runner-up's is then in ``runner_up``.
    """
    ev: dict = {"similarity": float(similarity), "field_fraction": float(field_fraction)}
    ev["tone_fit"] = float(ncc(image if toned is None else toned, drr, mask=mask)[0])
    try:
        ev["local_similarity"] = float(local_gradient_ncc(image, drr, mask=mask)[0])
    except NoWindowError:  # no window half inside the field: not judged (min_field_fraction judges such a field)
        ev["local_similarity"] = None
    ev["search"] = ("off" if search_off else "none") if search is None else ("ran" if search_ran else "skipped")
    ev["network_gap"] = None
    if network_pose is not None:
        ev["network_gap"] = dict(zip(("deg", "mm", "depth_mm"), np.round(pose_gap(network_pose, pose), 3).tolist()))
    ev["depth_drop"] = None
    if depth_scores is not None:
        d = np.asarray(depth_scores, float).reshape(3)
        ev["depth_drop"] = float(d[0] - max(d[1], d[2]))
    ev["depth_profile"] = None
    if profile is not None:
        here, scores = float(profile[0]), np.asarray(profile[1], float).reshape(2)
        ev["depth_profile"] = {"drop": here - float(scores.max()), "similarity": here, "scores": scores.tolist()}
    ev["rival"] = None if rival_pose is None else dict(rival_pose)
    ev["refined_tones"] = None if refined_tones is None else [float(t) for t in refined_tones]
    ev["runner_up"] = runner_up(search, pose, sod_mm, refined_tones) if search_ran else None
    if search_ran and search is not None and search.get("refined"):
        ev["alternatives"] = len(search["refined"]) - 1
    return ev


def runner_up(search: dict | None, pose: np.ndarray, sod_mm: float, tones=None) -> dict | None:
    """The best of the global search's refined starts (``search["refined"]`` similarities,
    ``search["refined_params"]`` deg/mm) that is :func:`distinct` from ``pose`` ``(4, 4)``:
    ``{"similarity", "deg", "mm", "depth_mm", "index"}`` (its gap, :func:`pose_gap`, and its place
    among the starts; with ``tones``, each start's tone fit, also its ``"tone_fit"``), or None (no
    search, or every start ended at the same answer)."""
    if search is None or not search.get("refined"):
        return None
    best = None
    for i, (s, p) in enumerate(zip(search["refined"], search["refined_params"])):
        gap = pose_gap(pose_from_params(np.asarray(p, float), sod_mm), pose)
        if distinct(gap) and (best is None or s > best["similarity"]):
            best = {"similarity": float(s), "deg": round(gap[0], 3), "mm": round(gap[1], 3), "depth_mm": round(gap[2], 3),
                    "index": i}
    if best is not None and tones is not None:
        best["tone_fit"] = float(tones[best["index"]])
    return best


def failure(evidence: dict, settings: VerdictSettings) -> str | None:
    """Why ``evidence`` is ``failed`` (the similarity or the tone fit below its floor), or None."""
    s = settings
    sim_, tone = evidence["similarity"], evidence["tone_fit"]
    if not np.isfinite(sim_) or sim_ < s.fail_below:
        return f"similarity {sim_:.2f} < {s.fail_below:.2f}: the DRR does not match the X-ray"
    if not np.isfinite(tone) or tone < s.tone_fail_below:
        return f"tone fit {tone:.2f} < {s.tone_fail_below:.2f}: the X-ray's intensities disagree with the CT's at this pose"
    return None


def checks(evidence: dict, settings: VerdictSettings) -> list[tuple[str, bool, str]]:
    """The checks a ``registered`` verdict needs, each ``(setting, passed, reason)``: the
    :class:`VerdictSettings` field that sets its threshold, whether ``evidence`` passes it, and
    the sentence that says so (a doubt where it failed). A check whose evidence was not gathered,
    or whose threshold is None, is left out. ``benchmarks/verdict.py --calibrate`` varies each
    setting against its own check."""
    s = settings
    sim_, tone = evidence["similarity"], evidence["tone_fit"]
    what = "local similarity" if evidence.get("similarity_metric") == "local_gncc" else "similarity"
    out = [("min_similarity", sim_ >= s.min_similarity,
            f"{what} {sim_:.2f}" if sim_ >= s.min_similarity else f"{what} {sim_:.2f} < {s.min_similarity:.2f}"),
           ("min_tone_fit", tone >= s.min_tone_fit,
            f"tone fit {tone:.2f}" if tone >= s.min_tone_fit else f"tone fit {tone:.2f} < {s.min_tone_fit:.2f}")]
    local = evidence.get("local_similarity")
    if local is not None and s.min_local_similarity is not None:
        ok = local >= s.min_local_similarity
        judged_by_it = what == "local similarity"  # the similarity above is this one: said once
        out.append(("min_local_similarity", ok, ("searched again and judged by local similarity" if judged_by_it else
                                                 f"local similarity {local:.2f}") if ok else
                    f"the edges agree as a whole but not window by window: local similarity {local:.2f} < "
                    f"{s.min_local_similarity:.2f} (one strong edge, such as the body's outline, can carry the whole "
                    "image's similarity)"))
    runner = evidence.get("runner_up")
    if evidence["search"] == "ran":
        if runner is not None and sim_ - runner["similarity"] < s.min_margin:
            out.append(("min_margin", False, f"a distinct pose ({runner['deg']:.0f} deg, {runner['mm']:.0f} mm across and "
                        f"{runner.get('depth_mm', 0):.0f} mm in depth away) scored {runner['similarity']:.2f}, within "
                        f"{s.min_margin:.2f} of it"))
        else:
            out.append(("min_margin", True, f"no distinct pose of the search scored within {s.min_margin:.2f}"
                        if runner is not None else "the search found no distinct pose"))
        if runner is not None and "tone_fit" in runner and s.min_joint_margin is not None:
            margin = sim_ + tone - runner["similarity"] - runner["tone_fit"]
            ok = margin >= s.min_joint_margin
            out.append(("min_joint_margin", ok, f"similarity plus tone fit {margin:+.2f} against the runner-up's"
                        if ok else f"a distinct pose of the search ({runner['deg']:.0f} deg, {runner['mm']:.0f} mm across "
                        f"and {runner.get('depth_mm', 0):.0f} mm in depth away) scores as well on similarity and tone fit "
                        f"together: this pose {margin:+.2f} against it (< {s.min_joint_margin:+.2f})"))
    elif evidence["search"] == "none" and s.sure_similarity is not None:  # a method without the search
        ok = sim_ >= s.sure_similarity
        out.append(("sure_similarity", ok, f"similarity {sim_:.2f} >= {s.sure_similarity:.2f} without a search" if ok
                    else f"no alternative examined (a method without the search) and similarity {sim_:.2f} < "
                    f"{s.sure_similarity:.2f}"))
    drop = evidence.get("depth_drop")
    if drop is not None:
        out.append(("min_depth_drop", drop >= s.min_depth_drop,
                    f"depth: +-{DEPTH_PROBE_MM:.0f} mm scores {drop:.3f} lower" if drop >= s.min_depth_drop else
                    f"the depth is not determined: {DEPTH_PROBE_MM:.0f} mm nearer or farther scores within "
                    f"{max(drop, 0.0):.3f} (< {s.min_depth_drop:.3f})"))
    profile = evidence.get("depth_profile")
    if profile is not None and s.min_profile_drop is not None:
        ok = profile["drop"] >= s.min_profile_drop
        out.append(("min_profile_drop", ok, f"depth profile: +-{DEPTH_PROBE_MM:.0f} mm, fitted again, scores "
                    f"{profile['drop']:.3f} lower" if ok else f"the depth is not determined: {DEPTH_PROBE_MM:.0f} mm "
                    f"nearer or farther, the other parameters fitted again, scores within {max(profile['drop'], 0.0):.3f} "
                    f"(< {s.min_profile_drop:.3f})"))
    other = evidence.get("rival")
    if other is not None and s.max_rival_gain is not None:
        away = distinct((other["deg"], other["mm"], other["depth_mm"])) or other["depth_mm"] > RIVAL_DISTINCT_DEPTH_MM
        ok = not (other["gain"] > s.max_rival_gain and away)
        out.append(("max_rival_gain", ok, f"no distinct pose nearby scores more than {s.max_rival_gain:.2f} higher on "
                    "similarity and tone fit together" if ok else f"a distinct pose nearby ({other['deg']:.0f} deg, "
                    f"{other['mm']:.0f} mm across and {other['depth_mm']:.0f} mm in depth away) scores {other['gain']:.2f} "
                    f"higher on similarity and tone fit together (> {s.max_rival_gain:.2f}): similarity "
                    f"{other['similarity']:.2f}, tone fit {other['tone_fit']:.2f}"))
    frac = evidence["field_fraction"]
    out.append(("min_field_fraction", frac >= s.min_field_fraction,
                f"{100 * frac:.0f} % of the X-ray used" if frac >= s.min_field_fraction else
                f"{100 * frac:.0f} % of the X-ray used (< {100 * s.min_field_fraction:.0f} %)"))
    return out


def judge(evidence: dict, settings: VerdictSettings | None = None) -> Verdict:
    """The verdict on ``evidence`` (:func:`gather_evidence`) with ``settings``: ``failed`` where the
    similarity or the tone fit is below its floor (:func:`failure`); ``registered`` where every
    check (:func:`checks`) passes; ``doubtful`` otherwise. Each check that decided it gives a reason."""
    s = settings or VerdictSettings()
    why = failure(evidence, s)
    if why is not None:
        return Verdict("failed", (why,), evidence)
    done = checks(evidence, s)
    doubts = tuple(reason for _, ok, reason in done if not ok)
    if doubts:
        return Verdict("doubtful", doubts, evidence)
    return Verdict("registered", tuple(reason for name, _, reason in done if name != "min_field_fraction"), evidence)


def judge_result(result, image: np.ndarray, *, render, sod_mm: float, mask: np.ndarray | None = None,
                 toned: np.ndarray | None = None, field_fraction: float | None = None,
                 settings: VerdictSettings | None = None, refine: CMAESRegistration | None = None,
                 rival_search: CMAESRegistration | None = None, search_off: bool = False) -> Verdict:
    """The verdict on an engine's :class:`register.engines.result.RegistrationResult` of ``image``
    ``(h, w)`` (its ``mask`` and ``toned`` version as registered). ``render``: ``(B, 4, 4) -> (B, h,
    w)`` line DRRs at the image's geometry (the tone fit's at ``result.pose`` and the depth probe's,
    :func:`depth_probe_poses`, scored by the refinement's similarity: tone-tolerant gradient NCC for
    a display image, gradient NCC otherwise); ``sod_mm``: the geometry's source-object distance (the
    poses of the search's refined starts); ``field_fraction``: the share of pixels used (default:
    the mask's); ``refine``: the refinement's CMA-ES as it scored the image (the depth profile,
    :func:`depth_profile`; None: not profiled); ``rival_search``: a line-DRR CMA-ES at the image's
    size (the rival, :func:`rival`; None: not searched); ``search_off``: :func:`gather_evidence`'s.

    A pose the pipeline searched again by local similarity (the search record's ``rescue`` kept
    ``"rescued"``, :func:`register.engines.pipeline.rescue`) is judged by the similarity that found
    it: its similarity and its runner-ups' are local similarities, and so are the depth probe's,
    the depth profile's and the rival's edge score (``local_gncc``); the evidence's
    ``similarity_metric`` names the one used."""
    search = result.search
    ran = search is not None and bool(search.get("grid_poses"))
    network = None
    if result.trajectory is not None and len(result.trajectory.get("params", ())):
        network = pose_from_params(np.asarray(result.trajectory["params"][-1], float), sod_mm)
    if field_fraction is None:
        field_fraction = 1.0 if mask is None else float(np.mean(mask))
    rescued = ((search or {}).get("rescue") or {}).get("kept") == "rescued"
    metric = "local_gncc" if rescued else ("tone_tolerant_gncc" if toned is not None else "gncc")
    drrs = np.asarray(render(depth_probe_poses(result.pose)), float)
    depth = bind_metric(metric, image, mask)(drrs)
    tones = None
    if ran and search.get("refined_params"):  # each refined start's tone fit: is a rival's intensities' fit as good?
        starts = np.array([pose_from_params(np.asarray(p, float), sod_mm) for p in search["refined_params"]])
        tones = ncc(image if toned is None else toned, np.asarray(render(starts), float), mask=mask)
    if rescued and refine is not None:
        refine = refine.scored_by((metric,) * len(refine.settings.levels))
    profile = None if refine is None else depth_profile(refine, image, result.params, mask=mask)
    other = None if rival_search is None else rival(rival_search, image, result.params, toned=toned, mask=mask,
                                                    edge_metric=metric if rescued else None)
    ev = gather_evidence(similarity=result.similarity, pose=result.pose, image=image, mask=mask, drr=drrs[0],
                         toned=toned, search=search, search_ran=ran, network_pose=network, sod_mm=sod_mm,
                         field_fraction=field_fraction, depth_scores=depth, profile=profile, rival_pose=other,
                         refined_tones=tones, search_off=search_off)
    ev["similarity_metric"] = metric
    return judge(ev, settings)
