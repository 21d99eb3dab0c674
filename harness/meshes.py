"""A big mesh for the benchmark and the test of a shape job's set-up (``python -m bench.big_mesh``,
``tests/e2e/test_big_setup_fairness.py``): a UV sphere of any size and the one-sensor scene that
optimizes its vertices. numpy only; write it with ``services.solver.scene.shape.ply_bytes``."""

from __future__ import annotations

import numpy as np

#: A 16x16 view of ``sphere.ply`` under constant light, direct illumination, one sample per pixel:
#: what is costly in such a job is its set-up, not its renders.
SPHERE_SCENE = """<scene version="3.0.0">
  <integrator type="direct"/>
  <sensor type="perspective" id="view-0"><float name="fov" value="35"/>
    <transform name="to_world"><lookat origin="0, 0.7, 2" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
      <rfilter type="box"/></film>
    <sampler type="independent"><integer name="sample_count" value="1"/></sampler></sensor>
  <shape type="ply" id="sphere"><string name="filename" value="sphere.ply"/><bsdf type="diffuse"/></shape>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
</scene>"""


def uv_sphere(rings: int) -> tuple[np.ndarray, np.ndarray]:
    """A sphere of radius 0.5: ``rings`` latitude rings of ``rings + 2`` vertices and two poles
    (``rings x (rings + 2) + 2`` vertices); vertices ``(V, 3)`` float32 and faces ``(F, 3)``
    int64, wound outwards."""
    segments = rings + 2
    theta = np.linspace(0, np.pi, rings + 2)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    vertices = np.concatenate([[[0, 1, 0]], ring, [[0, -1, 0]]]) * 0.5
    south = len(vertices) - 1

    def index(r, s):
        return 1 + r * segments + s % segments

    s = np.arange(segments)
    r = np.arange(rings - 1)[:, None]
    a, b, c, d = index(r, s), index(r, s + 1), index(r + 1, s), index(r + 1, s + 1)
    faces = np.concatenate([
        np.stack([np.zeros_like(s), index(0, s + 1), index(0, s)], -1),
        np.stack([np.stack([a, b, d], -1), np.stack([a, d, c], -1)], 2).reshape(-1, 3),
        np.stack([np.full_like(s, south), index(rings - 1, s), index(rings - 1, s + 1)], -1)])
    return vertices.astype(np.float32), faces.astype(np.int64)
