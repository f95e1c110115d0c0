"""[wall] scenes: the one-line errors before any work, a short `vesflow run` of runs/container.toml,
the collision check against the wall (docs/explanation/walls.md)."""
import os
import re
import subprocess
import sys

import h5py
import numpy as np
import pytest

from tests.harness import ROOT
from vesflow import shapes
from vesflow.errors import SceneError
from vesflow.layerpot.wall import Wall
from vesflow.parallel import Partition
from vesflow.scene import parse_scene
from vesflow.setup_state import wall_coefficients
from vesflow.stepping.poststep import PostStep
from vesflow.timing import NullTimers

SCENE = """
[wall]
shape = "sphere"
radius = 3.0
p = 12
[[vesicle]]
center = {center}
"""


@pytest.mark.parametrize("center,what", [("[5.0, 0.0, 0.0]", "outside the container"),
                                         ("[0.0, 0.0, 2.5]", "crossing the wall or too close to it"),
                                         ("[0.0, 1.97, 0.0]", "crossing the wall or too close to it")])
def test_vesicle_outside_or_against_the_container_is_a_scene_error(center, what):
    with pytest.raises(SceneError, match=rf"^vesicle\[0\]: centre .*: {what} \(\[wall\] sphere.* is -?[0-9.e-]+$"):
        parse_scene(SCENE.format(center=center))
    assert parse_scene(SCENE.format(center="[0.0, 1.9, 0.0]")).wall.axes == (3.0, 3.0, 3.0)


def test_rotated_ellipsoid_container():
    text = '[wall]\nshape = "ellipsoid"\naxes = [4.0, 2.0, 2.0]\nrotation = [0.0, 90.0, 0.0]\n[[vesicle]]\ncenter = {c}\n'
    parse_scene(text.format(c="[0.0, 0.0, 2.5]"))                 # along the long axis (now z)
    with pytest.raises(SceneError, match="outside the container"):
        parse_scene(text.format(c="[2.5, 0.0, 0.0]"))
    w = parse_scene(text.format(c="[0.0, 0.0, 0.0]")).wall
    X = wall_coefficients(w)[:, 0] / np.sqrt(4 * np.pi)
    assert np.allclose(X, 0.0)


@pytest.mark.parametrize("extra,key", [("[domain]\nperiod = 10.0\n", "wall"),
                                       ('[flow]\ntype = "shear"\nrate = 1.0\n', "flow.type"),
                                       ("", "wall.p")])
def test_wall_with_a_periodic_domain_a_flow_or_a_bad_degree(extra, key):
    text = extra + SCENE.format(center="[0.0, 0.0, 0.0]")
    if key == "wall.p":
        text = text.replace("p = 12", "p = 4")
    with pytest.raises(SceneError, match=rf"^{key}( = \S+)?: "):
        parse_scene(text)


def test_crossing_the_wall_is_a_collision():
    p = 6
    wall = Wall(wall_coefficients(parse_scene(SCENE.format(center="[0.0, 0.0, 0.0]")).wall), 12)
    post = PostStep({}, p, None, None, None, NullTimers(), None, lambda: 2 * p)
    post.wall = wall
    post.part = Partition.single(1)
    inside = shapes.make_shape("sphere", p, center=(0.0, 0.0, 1.8))[None]
    crossing = shapes.make_shape("sphere", p, center=(0.0, 0.0, 2.2))[None]
    beyond = shapes.make_shape("sphere", p, center=(0.0, 0.0, 6.0))[None]
    assert not post.touching(inside)
    assert post.touching(crossing) and post.touching(beyond)


def test_container_run(tmp_path):
    """runs/container.toml in its small variant: the wall is written once (/wall, the XDMF's second
    grid, PREFIX_wall.vtp of the VTK export), drawn translucent by vesflow render; the vesicles settle."""
    out = tmp_path / "c.h5"
    r = subprocess.run([sys.executable, "-m", "vesflow", "run", str(ROOT / "runs" / "container.toml"), "-o", str(out),
                        "-options_file", str(ROOT / "runs" / "small.opts")],
                       capture_output=True, text=True, timeout=600, env=dict(os.environ, OMP_NUM_THREADS="1"), cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    with h5py.File(out) as f:
        pts, tri = f["wall/points"][:], f["wall/triangles"][:]
        assert f["wall"].attrs["p"] == 16 and pts.shape == (2 * 16 * 17, 3)
        assert np.allclose(np.linalg.norm(pts, axis=1), 3.0, rtol=1e-12) and tri.max() == len(pts) - 1
        c = f["frames/centroid"][:]
    pv = pytest.importorskip("pyvista")
    os.environ.setdefault("HDF5_USE_FILE_LOCKING", "FALSE")
    r = pv.XdmfReader(str(out.with_suffix(".xmf")))         # ParaView's reader: the frames, then the wall
    r.set_active_time_value(r.time_values[-1])
    blocks = r.read()
    assert len(blocks) == 2 and np.array_equal(np.asarray(blocks[1].points), pts)
    from vesflow.vtk_export import export_vtk
    export_vtk(out, tmp_path / "vtk")
    wall = pv.read(tmp_path / "vtk" / "c_wall.vtp")
    assert wall.n_points == len(pts) + 2 and wall.n_cells == 2 * len(pts)
    from PIL import Image

    from vesflow.render import render
    res = render(out, movie=False, frames_dir=tmp_path / "png", frames=[len(c) - 1], color="none", size=(320, 240))
    img = np.asarray(Image.open(res.frames[0]).convert("RGB"), dtype=float)
    wall_like = np.all(np.abs(img - [205, 214, 224]) < 25, axis=-1).mean()     # the translucent wall over white
    print(f"render: {wall_like:.2f} of the frame shows the wall")
    assert wall_like > 0.15
    dz = c[-1, :, 2] - c[0, :, 2]
    print(f"settled by {dz} in t = 0.15")
    assert np.all(dz < 0) and np.all(np.abs(c[-1, :, :2] - c[0, :, :2]) < np.abs(dz)[:, None])


@pytest.mark.parametrize("how", ["two ranks", "explicit coupling"])
def test_what_walls_cannot_do_is_refused_before_the_output_file(how, tmp_path):
    out = tmp_path / "x.h5"
    cmd = [sys.executable, "-m", "vesflow", "run", str(ROOT / "runs" / "container.toml"), "-o", str(out),
           "-options_file", str(ROOT / "runs" / "small.opts")]
    if how == "two ranks":
        mpiexec = os.path.join(os.path.dirname(sys.executable), "mpiexec")
        if not os.path.exists(mpiexec):
            pytest.skip("no mpiexec beside the interpreter")
        cmd, want = [mpiexec, "-n", "2"] + cmd, r"\[wall\]: walls need one rank \(this run has 2 MPI processes\)"
    else:
        cmd, want = cmd + ["-ves_coupling", "explicit"], "-ves_coupling explicit: a \\[wall\\] needs the implicit coupling"
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=dict(os.environ, OMP_NUM_THREADS="1"),
                       cwd=ROOT)
    assert r.returncode == 2 and not out.exists()
    assert re.search(want, r.stderr), r.stderr[-500:]


def test_repulsion_from_the_wall_pushes_a_vesicle_back():
    """(3.13) against the wall: on a sphere 0.1 from the wall of a spherical container the force
    points away from the wall and is the sum of the formula over its points near the wall; none
    when the gap exceeds 5 R."""
    from vesflow import repulsion
    from vesflow.surface import Surface
    p, R = 8, 0.05
    wall = Wall(wall_coefficients(parse_scene(SCENE.format(center="[0.0, 0.0, 0.0]")).wall), 12)
    for z, gap in ((1.9, 0.1), (1.0, 1.0)):
        S = Surface(shapes.make_shape("sphere", p, center=(0.0, 0.0, z))[None], p)
        X = S.points().reshape(-1, 3)
        f = repulsion.wall_repulsion_force(S, wall.targets(X), R, 2 * p)
        F = S.geometry(2 * p).integrate(f)[0]
        d = 3.0 - np.linalg.norm(X, axis=1)                       # exact distances to the sphere r = 3
        on = d < 5 * R
        expect = -(R * R / d[on] ** 2 * np.exp(-(d[on] / R) ** 2))[:, None] * X[on] / np.linalg.norm(X[on], axis=1)[:, None]
        print(f"gap {gap}: force {F}, {on.sum()} points within 5 R")
        if gap > 5 * R:
            assert not on.any() and np.abs(F).max() == 0.0
        else:
            assert F[2] < 0 and abs(F[0]) + abs(F[1]) < 1e-10 * abs(F[2])
            # the force is filtered to degree p (as the vesicles'): its total against the p-grid sum of (3.13)
            F_grid = (expect * S.geometry(p).dA.reshape(-1)[on][:, None]).sum(axis=0)
            print(f"  total {F[2]:.6e}, p-grid sum of (3.13) {F_grid[2]:.6e}")
            assert abs(F[2] / F_grid[2] - 1) < 1e-2


def test_check_estimates_the_wall():
    """`vesflow check`'s estimate has the wall's share (vesflow.costs._wall_cost): its memory is
    3 (3 C_w)^2 doubles and it counts the vesicle points within h_w = sqrt(A_w / q_w), q_w = 4 p_w."""
    from vesflow import costs
    from vesflow.surface import Surface
    sc = parse_scene(SCENE.format(center="[0.0, 0.0, 1.0]"))
    est = costs.estimate(sc)
    Cw = 13 ** 2 - 1
    assert est.wall_p == 12 and est.mem_wall == 3 * (3 * Cw) ** 2 * 8 and est.t_wall > 0
    h_w = np.sqrt(4 * np.pi * 9 / 48)                               # 1.53
    X = Surface(shapes.make_shape("sphere", 16, center=(0.0, 0.0, 1.0))[None], 16).points().reshape(-1, 3)
    near = np.count_nonzero(3.0 - np.linalg.norm(X, axis=1) < h_w)
    assert 0 < near < len(X) and est.wall_near_points == near
    assert costs.estimate(sc, {"wall_q": 96}).wall_near_points < near           # a finer rule: a thinner zone
    free = costs.estimate(parse_scene("[[vesicle]]\n"))
    assert free.wall_p == 0 and free.t_wall == 0 and "wall" not in str(free) and "wall     p_w = 12" in str(est)


CROSSING = """
[discretization]
p = 6
[time]
horizon = 0.2
dt = 0.1
[output]
every = 0.1
[gravity]
g = [0.0, 0.0, -400.0]
[wall]
shape = "sphere"
radius = 3.0
p = 8
[[vesicle]]
center = [0.0, 0.0, -1.85]
excess_density = 1.0
bending_modulus = 0.1
"""


def test_a_single_vesicle_driven_into_the_wall_is_stopped_by_collisions(tmp_path):
    """One vesicle (no other surface) pushed 0.15 from the wall: the steps that would cross it
    are rejected as collisions and halved; the accepted states stay inside."""
    scene, out = tmp_path / "cross.toml", tmp_path / "cross.h5"
    scene.write_text(CROSSING)
    r = subprocess.run([sys.executable, "-m", "vesflow", "run", str(scene), "-o", str(out), "-ts_type", "euler",
                        "-ves_adapt", "none", "-ts_max_steps", "2"], capture_output=True, text=True, timeout=300,
                       env=dict(os.environ, OMP_NUM_THREADS="1"), cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    with h5py.File(out) as f:
        reason, accepted = f["steps/reason"][:], f["steps/accepted"][:]
        pts = f["frames/points"][-1]
    print(f"reasons {reason.tolist()}, accepted {accepted.tolist()}")
    assert accepted.sum() == 2 and np.count_nonzero(reason == 3) >= 2          # 3: collision
    assert np.linalg.norm(pts.reshape(-1, 3), axis=1).max() < 3.0


def test_the_wall_density_is_in_the_checkpoint():
    from vesflow.stepping.state import State
    st = State.initial(np.zeros((1, 3, 8)), 8)
    st.guess, st.wall = True, np.arange(6.0)
    back = State.from_checkpoint(st.as_checkpoint())
    assert np.array_equal(back.wall, st.wall) and State.from_checkpoint(State.initial(np.zeros((1, 3, 8)), 8)
                                                                         .as_checkpoint()).wall is None
