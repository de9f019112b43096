"""Tuning of the fast matcher, in a module of its own: every stage reads it, none imports the orchestrator.

:class:`FastOptions` is handed by :func:`mapdb.match.fast.match_fast` to each stage in turn
(:mod:`~mapdb.match.hypotheses`, :mod:`~mapdb.match.screen`, :mod:`~mapdb.match.rivals`).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["FastOptions"]


@dataclass(frozen=True)
class FastOptions:
    """Tuning of :func:`match_fast`; the defaults are the ones the benchmarks measured.

    Attributes
    ----------
    map_neighbours, image_neighbours : int
        Neighbours per anchor object whose triples form quads, in the map and in the image.
    pixel_sigmas : tuple of float
        Assumed pixel error (1 sigma) of the lookup passes, tried in order (each over all anchor
        batches) until a match is accepted.
    tolerance_factor : float
        Lookup radius in units of the quad invariant's predicted standard error (2.0 ~ 99% in 4-D).
    max_invariant_radius : float
        Image quads needing a wider lookup radius (tiny quads) are not looked up.
    max_hits_per_quad : int
        At most this many nearest map quads per lookup.
    max_verified : int
        Hypotheses screened per round, those whose pose most others share first
        (:func:`~mapdb.match.hypotheses.prioritise`).  Andorra's images bring 57-134 a round, so 256 rarely
        binds there; a 5M-object world (245 jittered copies of three towns) brings
        500-830 (chance hits of a key space of 183 million quads: a world without near-copies brings as
        many), and the screen's KD-tree queries grew with them.
        At 256 (3,000 before) that world's lost-in-space answers cost 0.85x the CPU time, 99 of 100 answers
        the same (``python benchmarks/lost_in_space_index.py --lookups-only --worlds 5000000 --jitter 2
        --baseline 0ef3d71``); Andorra's, the rendered masks' and the paper bench's answers were kept, bar two
        rendered images it improved.  128 answered one world image wrongly.
    screen_objects : int
        Image objects (around each hypothesis's quad) used to screen hypotheses; the shortlist is
        tested on all objects.
    anchors_per_batch : int
        Image objects (nearest the centre first) whose quads are looked up together; the search stops
        at the first batch that gives an accepted match.
    shortlist : int
        Best screened hypotheses given the full test.
    refine_candidates : int
        Distinct places per round given the decision test and refined.
    log10_epsilon : float
        Accept when log10 NFA is below this.
    ambiguity_margin : float
        Reject as ambiguous when a distinct runner-up is accepted too and scores within this of the best.
    density_radius_factor : float
        Local label densities are counted within this many footprint half-diagonals of the answer.
    max_candidates : int
        Runners-up reported.
    max_sigma_m : float or None
        Withhold (reject as imprecise, listing it as a candidate) an answer whose estimated 1-sigma
        position error exceeds this many metres: a few objects in one corner of the image place its
        centre poorly, and an answer metres off is worse than none.
    max_objects : int
        An image with more objects is matched on the ``max_objects`` nearest its centre (ties broken
        by input order): the decision's cost grows with the square of the objects, and a few hundred
        objects place an image as well as thousands.  This bounds memory and time per image.
    density_neighbours : int
        The decision's label density around each projected image object comes from the distance to
        its ``density_neighbours``-th nearest map object of its label (0: one density per label around
        the answer, as the ranking uses).
    max_batches : int
        Anchor batches tried per lookup pass: an image that matches nowhere costs at most
        ``len(pixel_sigmas) * max_batches`` rounds, whatever its number of objects.
    ambiguity_anchors : int
        The winner's inliers (nearest the image centre) whose quads are looked up again in the quad indexes
        for far places holding the same pattern (:mod:`mapdb.match.rivals`; 0, the default: the repeats
        within the footprint and the search's runner-ups only, about 15 % less time an image).
    ambiguity_places : int
        At most this many other places (runner-ups, repeats, look-up hits; those where most image objects
        land near a map object first) are refitted beside the winner.
    areas : bool
        Weigh the objects' pixel areas (``area_px``) against the map's stored areas
        (:mod:`mapdb.match.evidence.areas`); False answers as if the objects carried no areas (``mapdb query
        --no-areas``).
    """

    map_neighbours: int = 8
    image_neighbours: int = 5
    pixel_sigmas: tuple[float, ...] = (1.5, 4.0)
    tolerance_factor: float = 2.0
    max_invariant_radius: float = 0.3
    max_hits_per_quad: int = 16
    max_verified: int = 256
    screen_objects: int = 12
    anchors_per_batch: int = 6
    shortlist: int = 16
    refine_candidates: int = 4
    log10_epsilon: float = -4.0
    ambiguity_margin: float = 1.0
    density_radius_factor: float = 1.5
    max_candidates: int = 5
    max_sigma_m: float | None = 1.0
    max_objects: int = 256
    density_neighbours: int = 6
    max_batches: int = 8
    ambiguity_anchors: int = 0
    ambiguity_places: int = 8
    areas: bool = True
