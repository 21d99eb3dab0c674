"""The built-in scenes, by name, as clients see them (the solver builds them:
``services.solver.scene.builtin``, which checks at import that it builds exactly these)."""

from __future__ import annotations

BUILTIN_SCENES: dict[str, str] = {
    "cornell-box": "Mitsuba's Cornell box (mi.cornell_box()).",
    "hidden-object": "Closed room; the optimized sphere is behind the camera and reaches the image only "
                     "through interreflection (paper Fig. 5).",
    "mirror-box": "Cornell box whose back wall is a perfect mirror, with a blue sphere.",
    "glossy-box": "Cornell box with a rough gold sphere (GGX roughness 0.15) reflecting the walls.",
    "closet-box": "Cornell box with a closed cube hiding a red sphere: no camera path reaches the sphere, "
                  "so `choose_effects` drops its parameters.",
    "room-closed-8": "Closed room (walls.reflectance.value) with a sphere in sight (ball.reflectance.value), seen "
                     "by 8 cameras of 128x128: multi-view, long light paths.",
    "room-open-8": "The same room without its front wall (light escapes): multi-view, shorter paths.",
    "textured-box": "Cornell box without its blocks whose back wall has a 64x64 albedo texture "
                    "(wall.reflectance.data, 12,288 scalars), seen by 4 cameras of 128x128: texture recovery.",
    "textured-floor": "The same box whose floor has a 16x16 albedo texture (floor-paint.reflectance.data, 768 "
                      "scalars), hidden from its 2 cameras of 32x32 that look up at the walls it lights: a texture "
                      "acting through interreflection.",
    "pose-block": "A block (a generated mesh, 8 shared corners) on a floor under an area light, seen by 2 cameras "
                  "of 32x32: geometry, the block's pose (block.to_world.translate, block.to_world.rotate).",
    "shape-sphere": "A sphere (a generated icosphere, 642 vertices) under a constant sky and an area light, seen by "
                    "6 cameras of 32x32 around it: geometry, the sphere's shape (sphere.vertex_positions) recovered "
                    "towards a deformed target (targets.synthetic.meshes).",
}
