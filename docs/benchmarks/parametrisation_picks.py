"""The automatic parametrisation of bench hard's captures and the rule-check scenes,
without rendering (issue 34): cameras as `nerfgauge bench hard` plans them (40 views),
the opaque share from rays cast against the ground-truth meshes (16 px), and the pick
before (no closure evidence) and now. Run from the repository root."""
import sys

sys.path.insert(0, "tests")
from test_parametrisation import _planned_capture  # noqa: E402
from nerfgauge.nerf.parametrisation import choose_parametrisation  # noqa: E402
from nerfgauge.scenes import CHECK_SCENES, HARD_SCENES  # noqa: E402

for scene in HARD_SCENES + CHECK_SCENES:
    aabb, c2w, opaque = _planned_capture(scene)
    before = choose_parametrisation(None, aabb, c2w, None)[0]
    now, reason = choose_parametrisation(None, aabb, c2w, opaque)
    print(f"| {scene} | {100 * opaque:.1f}% | {before} | {now} | {reason} |")
