"""Names of the synthetic shapes and tube options, importable without the renderer."""

SHAPES = ("bend_rotate", "s_curve", "loop", "straight", "three_segments", "helix")
# A seeded random smooth shape (pipeline.synth.random_shapes); not one of the named SHAPES.
RANDOM_SHAPE = "random"
TIPS = ("flat", "round")
PROFILES = ("uniform", "tapered", "disks", "step")
IMAGE_SIZES = ((320, 240), (1280, 960))
# The camera placements (pipeline.synth.rig.ARRANGEMENTS holds each camera's pose).
ARRANGEMENT_NAMES = ("oblique", "ninety")
