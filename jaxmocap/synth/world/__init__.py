"""The independent test world (issue 16 item 6): sequences rendered by MuJoCo, not by the
trackers' own ray caster, with bodies of other proportions / names / primitives, a shirt of
another layout, spot lamps with shadows and highlights, clutter, occluders and camera effects,
written in the ``jaxmocap synth`` dataset layout. For evaluation only.

``spec`` (what a sequence shows), ``scene`` (the MJCF document), ``render`` (MuJoCo
rendering, dataset writing), ``split`` (the dev / test sequences, docs/results/test_world.md).
"""

from .render import WorldSequence, ensure_gl, render_world, write_world
from .spec import WorldError, WorldSpec, bands_garment, world_body, world_garment

__all__ = ["WorldSpec", "WorldError", "WorldSequence", "bands_garment", "ensure_gl",
           "render_world", "world_body", "world_garment", "write_world"]
