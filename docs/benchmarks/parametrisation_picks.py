"""The automatic parametrisation of bench hard's captures, the bench scenes and the
rule-check scenes, without rendering (issue 34): cameras as `nerfgauge bench hard` plans
them (40 views), the opaque share from rays cast against the ground-truth meshes (16 px),
the pick before (no closure evidence) and now, and whether the rule is unsure there, so a
run trials its pick against the alternative (issue 52; nerf.trials). Run from the
repository root."""
import sys

sys.path.insert(0, "tests")
from test_parametrisation import _planned_capture  # noqa: E402
from nerfgauge.nerf.parametrisation import choose_parametrisation, parametrisation_doubt  # noqa: E402
from nerfgauge.scenes import CHECK_SCENES, HARD_SCENES  # noqa: E402

print("| scene | opaque | pick without opacity | pick | trial | reason |")
print("|---|---|---|---|---|---|")
for scene in HARD_SCENES + ("primitives", "glossy", "random") + CHECK_SCENES:
    aabb, c2w, opaque = _planned_capture(scene)
    before = choose_parametrisation(None, aabb, c2w, None)[0]
    now, reason = choose_parametrisation(None, aabb, c2w, opaque)
    doubt = parametrisation_doubt(aabb, c2w, opaque)
    trial = "no" if doubt is None else f"{' vs '.join(doubt[0])}: {doubt[1]}"
    print(f"| {scene} | {100 * opaque:.2f}% | {before} | {now} | {trial} | {reason} |")
