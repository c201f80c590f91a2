"""Names of the synthetic shapes, importable without the renderer."""

SHAPES = ("bend_rotate", "s_curve", "loop", "straight", "three_segments", "helix")
