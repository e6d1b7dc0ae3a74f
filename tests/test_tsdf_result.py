"""The subject mesh crosses from the compute worker to the daemon as its arrays only: the daemon
unpickles it on a thread holding the interpreter lock its event loop needs."""

from __future__ import annotations

import pickle

import numpy as np
import trimesh

from planner.tsdf import TsdfResult


def test_a_tsdf_result_pickles_as_its_arrays_whatever_its_mesh_has_cached() -> None:
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=300.0)
    result = TsdfResult(mesh, frames_used=12, per_camera={"D0": 12}, timings_s={"total": 1.0})
    mesh.vertex_normals, mesh.face_adjacency, mesh.edges_unique  # caches a Trimesh pickles with itself
    data = pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL)
    arrays = np.asarray(mesh.vertices).nbytes + np.asarray(mesh.faces).nbytes
    assert len(data) <= 1.05 * arrays + 4096
    back = pickle.loads(data)
    assert np.array_equal(back.mesh.vertices, mesh.vertices) and np.array_equal(back.mesh.faces, mesh.faces)
    assert (back.frames_used, back.per_camera, back.timings_s) == (12, {"D0": 12}, {"total": 1.0})
