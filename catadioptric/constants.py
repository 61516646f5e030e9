"""Tuning constants of the catadioptric matcher, in one place.

Each constant says what it sets and why it has its value. The
measurements behind the values are in docs/design-notes.md (catadioptric).
Gates are in per-axis standard deviations of a pair's combined sphere
noise (:func:`catadioptric.sphere_noise` of both rays); "noise gates" are
multiples of :data:`GATE_SIGMAS` such deviations.

The matcher's modules read these names when they are imported: to change a
value for an experiment, patch it in the module that uses it.
"""

from __future__ import annotations

__all__ = [
    "CHANCE_ALPHA",
    "EPI_CLUSTER_DEG",
    "EPI_FINAL",
    "EPI_HYPOTHESES",
    "EPI_LO",
    "EPI_LO_GATE",
    "EPI_MATCHES",
    "EPI_MIN_PARALLAX",
    "EPI_OUTER",
    "EPI_RANSAC",
    "EPI_RIVAL",
    "EPI_SHAPE_TOL",
    "EPI_SHARE",
    "GATE_SIGMAS",
    "MIN_ESSENTIAL_PAIRS",
    "MIN_POSTERIOR",
    "PATTERN_ALPHA",
    "PEEL_OVERLAP",
    "PLANE_GROWTH",
    "PLANE_LOCAL",
    "PLANE_MATCHES",
    "PLANE_NEIGHBOURS",
    "PLANE_SIGNATURE_TOL",
    "PLANE_TRIALS",
    "PLANE_TRIALS_GROWN",
    "QUATERNION_SAMPLE",
    "REACH_SPACINGS",
    "RIVAL_ANCHORS",
    "RIVAL_RATIO",
    "RIVAL_SEEDS",
    "SHIFTED_MAPPINGS",
    "TRIANGLE_NEIGHBOURS",
    "WIDE_CLUSTER_FACTOR",
]

# ------------------------------------------------------------------ shared
#: Residual gate of a pair, in per-axis standard deviations of the pair's
#: combined noise: the norm of a 2D Gaussian residual (on the sphere's
#: tangent plane) stays below it with probability 0.99, so a true pair is
#: rarely gated out while the gate stays as small as the noise allows.
GATE_SIGMAS = 3.03

# ------------------------------------------------------------------ rotation search
#: Neighbours per ray for the local triangles of the rotation search: each
#: ray forms triangles with pairs of its 6 nearest rays (15 per ray), enough
#: that some triangle of a true ray survives outliers among its neighbours,
#: few enough that the triangle tables stay small.
TRIANGLE_NEIGHBOURS = 6
#: Trial rotations whose neighbour counts are taken, at most (a fixed random
#: subset beyond): the densest cluster is found as well from a sample, and
#: the count costs a ball query per trial.
QUATERNION_SAMPLE = 20000
#: Without a rotation that beats the chance level (a camera translation
#: spreads the triangles' rotations), the seeds of the locally rigid growth
#: come from a cluster this many times ``cluster_deg`` wide.
WIDE_CLUSTER_FACTOR = 2.5
#: A growth (locally rigid or along the epipolar arcs) predicts a ray only
#: within this many median match spacings of its nearest match: farther
#: out, the neighbours' motion says little about the ray's.
REACH_SPACINGS = 4.0

# ------------------------------------------------------------------ acceptance
#: A rigid or epipolar match is kept when its posterior probability of
#: being the ray's true partner (:func:`catadioptric.acceptance.posterior`)
#: reaches this: precision first. The posterior is calibrated (or
#: conservative) on the benchmark's scenes, and most true matches lie far
#: above this floor.
MIN_POSTERIOR = 0.8
#: Ambiguity test against repeated structure (a checkerboard matches itself
#: shifted by one square): a rival that explains at least this share of the
#: winner's pairs with other partners (and the chance level) makes the
#: answer ambiguous. Below the share ``(a - 1) / a >= 2/3`` of the pairs
#: that a one-period shift keeps on a pattern 3 or more periods wide, above
#: the chance-level rivals of scattered corners.
RIVAL_RATIO = 0.6
#: Winner pairs (nearest the anchor) shifted to seed a rival: enough for a
#: locally rigid growth to start (3 are needed), few enough to stay on one
#: patch, where a one-period shift is about one vector.
RIVAL_SEEDS = 8
#: Anchors of the rival search, spread over the matched rays, so that a
#: repeated pattern on one part of the view is found wherever it lies.
RIVAL_ANCHORS = 3
#: Level of the chance-level test (:func:`gatv.stats.chance_support`): a
#: wrong rotation's support exceeds the chance level with at most this
#: probability, small because a wrong answer costs more than a missed one.
CHANCE_ALPHA = 1e-6

# ------------------------------------------------------------------ epipolar stage
#: Radius (degrees) of the cluster of triangle rotations whose triangles
#: feed the RANSAC: with a camera translation the local triangles turn by
#: the parallax too, so the cluster is as wide as the parallax turns them.
EPI_CLUSTER_DEG = 15.0
#: Tolerance on the log side lengths of matched triangles for the RANSAC
#: pool: parallax changes a triangle's sides, more than the rotation
#: search's default ``shape_tolerance`` allows.
EPI_SHAPE_TOL = 0.25
#: Fewest pairs an essential matrix is estimated from or a growth along the
#: arcs may keep: 8 fix it, the rest check it.
MIN_ESSENTIAL_PAIRS = 12
#: RANSAC samples (three triangles each).
EPI_RANSAC = 2000
#: Distinct motions grown at most: the best-scored sample is not always the
#: right motion, growth along the arcs decides among a few.
EPI_HYPOTHESES = 6
#: Share of the best sample's score a rival motion needs to be grown too.
EPI_RIVAL = 0.5
#: LO-RANSAC: the best EPI_LO samples (scored with a gate EPI_LO_GATE times
#: the noise gate, since a minimal sample's essential matrix is rough) are
#: refitted on all their pairs and polished before they compete.
EPI_LO = 24
EPI_LO_GATE = 2.0
#: Growth rounds along the arcs with (R, t) refitted between them.
EPI_OUTER = 6
#: Gate of the last growth round, in noise gates (the plain noise gate).
EPI_FINAL = 1.0
#: Median arc angle of the matches, in sphere noise, below which the views
#: differ by a rotation only (``t`` undefined): the epipolar stage then
#: stands aside for the rigid one.
EPI_MIN_PARALLAX = 3.0
#: Target triangles retrieved per source triangle for the RANSAC pool (the
#: nearest in log side lengths): parallax and noise reorder the shapes of
#: small, crowded triangles, so the true partner often ranks far below the
#: 8 of the rotation search.
EPI_MATCHES = 32
#: Last round: a ray is also predicted by every plane of its neighbours that
#: at least this share of them agree with (both sides of a crease of the
#: scene; see :func:`catadioptric.epipolar.grow_epipolar`).
EPI_SHARE = 2.0 / 3.0

# ------------------------------------------------------------------ plane stage (further motions)
#: Neighbours per ray for the local quadruples of the plane stage: a ray and
#: three of its 5 nearest. A tilted plane foreshortens one direction, which
#: reorders the nearest neighbours; 5 keep the four grid neighbours of a
#: pattern corner under a 2:1 foreshortening.
PLANE_NEIGHBOURS = 5
#: Tolerance on a quadruple's affine signature (coordinates of its fourth
#: ray in the frame of the first three): a homography is affine only to
#: first order over a quadruple, and the corners carry noise.
PLANE_SIGNATURE_TOL = 0.15
#: View-2 quadruples retrieved per view-1 quadruple (nearest signatures).
PLANE_MATCHES = 8
#: Trial homographies at most (a seeded random subset beyond): scoring
#: them locally is cheap, growing them is not.
PLANE_TRIALS = 40000
#: Rays around a trial's quadruple on which it is scored before growth.
PLANE_LOCAL = 16
#: Trials grown (best local scores first, one per anchor ray).
PLANE_TRIALS_GROWN = 40
#: Neighbourhood sizes (nearest rays of the anchor) of the growth.
PLANE_GROWTH = (12, 24, 48, 96)
#: Level of the sign test between rival mappings of a repeated pattern: a
#: rival that explains more rays replaces the winner only when the rays
#: one explains and the other does not are this unlikely to split so
#: unevenly by chance (a shift by one period of an 8 x 6 pattern leaves
#: 6 or 8 corners unexplained: p = 0.016 or 0.004).
PATTERN_ALPHA = 0.05
#: A further motion is a new motion only when at most this share of its
#: pairs already fits an earlier motion (else it is more of that motion,
#: e.g. a wall of the scene seen by a moving camera, and the peeling stops).
PEEL_OVERLAP = 0.5
#: Mappings whose shifts by one period are grown in each round of the
#: repeated-structure check (the winner and the best supported): a
#: mapping shifted by several periods is walked back one period a round.
SHIFTED_MAPPINGS = 3
