"""Parts and joints over a whole video, from the per-pair motions and point labels of a finished run:
the built-in part finder, ``tracks``.

A rule that decides from motions gives every pair (i, j) its rigid motions and labels each point of
frame i (and, judged the other way, of frame j) with the motion that explains it. This package links
those per-pair segments through the frames into parts, and grows the tree of joints between them, one
module per step (:mod:`.tracks`, :mod:`.base`, :mod:`.joints`, :mod:`.tree`, :mod:`.images`;
:func:`.finder.find_articulation` runs them in order):

1. **Tracks.** A pair's motion and another pair's motion are the same part when their labelled points
   overlap (intersection over union of at least ``min_overlap``): on the same frame (a pair's source
   and an earlier pair's target are one cloud) or on neighbouring frames (the same pixels, which
   move little in one frame). Overlaps are merged greedily, largest first, never putting two motions
   of one pair into one part.
2. **Base.** The part found still (its motion below the rule's threshold) in the most pairs that
   show the object articulated: the hand moves the part it holds and leaves the base on the table,
   and the base need not be the largest part. When no part is ever still (the object is carried),
   the part with the most labelled points. A pair that found one motion saw the whole object move
   as one body: its motion is the base's.
3. **Base poses.** The base's motions are chained through the pairs into its pose in every frame,
   relative to the first frame. A motion the rule cannot tell from staying still (below its motion
   threshold, or in a pair it found without motion) is the identity: a fit that drags a still base
   by a fraction of a moving part's motion would otherwise carry its poses away, pair after pair.
   So is a motion between two pairs, from the frame before and the frame after, that saw the base
   still over all the pair's frames: a blend of the base's motion and a part's.
   Pairs (i, i + k) link only every k-th frame; the k interleaved chains
   are tied together by interpolating the first chain's poses in time (constant velocity).
   A small part's regions in two pairs may overlap too little to be linked in step 1; two of its
   tracks are then linked by their motions relative to the base, which for one joint are one
   velocity field scaled by each pair's change of state (within ``link_sigmas`` of the depth
   noise). Every part other than the base seen moving in at least ``min_pairs`` pairs is a moving
   part.
4. **Joints.** Each pair that sees a moving part and a candidate parent gives the part's motion
   relative to the parent, in the parent's coordinates at its state 0 (for the base: its coordinates
   of the first frame, the camera frame of frame 0 when the base does not move). For a
   one-degree-of-freedom joint each is ``exp(Δq ξ)``, one twist ξ whatever the pair, so the joint
   estimator is given the part's pose moved by each relative motion and by its inverse, and told
   that only one pose per pair is independent (so its chi-square tests and BIC count each pair's
   evidence once). The states per frame follow by least squares from the
   pairs' differences ``q_j - q_i = Δq``, the interleaved chains of pairs tied by a weak smoothness
   term between neighbouring frames.
5. **Tree.** Grown from the base, it attaches at each step the moving part whose joint on a part
   already in the tree has the lowest BIC per pose, as Sturm et al. choose the kinematic tree: the
   outer arm of a chain (a lamp's, a folding ruler's) hangs on the inner arm, relative to which it
   has one degree of freedom, not on the base. A joint's residuals that neighbouring pairs share are
   counted as misfit, not noise: a part carried along a curve by a linkage (a desk lamp's head)
   keeps its orientation relative to the base and passes for a slide there, but its travel turns
   from pair to pair. A joint that fewer than three pairs tell is taken only when no tested one is on
   offer: an axis passes through any two poses. Every joint and every part's points are given in the
   base's first-frame coordinates with all joints at state 0.
6. **Part images.** Each frame's segmentation comes from the parts' motions over the whole video,
   not from one pair's labels (which may be wrong near a seam, or missing where no pair separated
   the parts): each object point, moved by each part's motion to the frames where the parts' motions
   differ most, takes the part that puts it on the surface seen there, as multi-body trackers keep
   their segmentation consistent. Where the depth cannot tell (a part sliding along a surface puts
   the surface's points on it too), the texture can: the point takes the part whose motion leaves its
   intensity as it was. In a frame where no pair gave a part's state, the state is found
   first by looking the part's points up in the frame at each state of its joint. Where too few of
   them are found there (the part hidden, or turned away), the state is the one between the nearest
   frames that gave one (held at the ends of the video), and where no pair separated the parts
   either, each of the frame's points takes the part whose points, placed there by the joints, are
   nearest: every frame gets its parts, and a part hidden for a while keeps its track. A frame no
   pair reaches is labelled so too, with the base placed between the frames before and after it.
"""

from artclass_core import RunResult, hookimpl
from artclass_core.articulation import Articulation
from artclass_core.interfaces import JointEstimator, PartFinder

from .base import chain_interleaved, chain_pair_motions
from .finder import find_articulation
from .joints import estimate_joint, frame_states, smooth_misfit
from .params import PartsParams


class TracksPartFinder(PartFinder):
    """Parts tracked through the video from the pairs' motion labels, joined in a kinematic tree."""

    name = "tracks"
    description = (
        "links the pairs' motion segments through the video into parts, grows the kinematic tree by "
        "BIC and labels every frame from the parts' motions"
    )
    Params = PartsParams
    needs = "motions"

    def find(self, result: RunResult, *, estimator: JointEstimator, images: bool = True) -> Articulation:
        return find_articulation(result, estimator=estimator, params=self.params, images=images)


@hookimpl
def register_part_finders(register):
    register(TracksPartFinder)


__all__ = [
    "PartsParams",
    "TracksPartFinder",
    "chain_interleaved",
    "chain_pair_motions",
    "estimate_joint",
    "find_articulation",
    "frame_states",
    "smooth_misfit",
]
