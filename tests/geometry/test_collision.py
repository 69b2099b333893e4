"""CollisionTerm on real anny bodies: broad phase, exact depths against libigl, gradients that
separate both bodies, the Jiang pitfalls (same spot, thin penetrations), batching, bad input.

Scenes: body a in anny's rest A-pose with its pelvis at (0, 0.95, 0) facing +Z; body b the same
body turned 180 deg about +Y, shifted along Z (front to front: "hug", feet interleaved, ~9 cm
deep; back to back: shallow contacts) or 2 m along X ("far").
"""

from __future__ import annotations

import math

import igl
import numpy as np
import pytest
import torch

from dualhuman_builder.body.topology import collision_faces
from dualhuman_builder.geometry.collision import CollisionTerm

HUG_DZ = 0.15  # b in front of a, front to front
BACK_DZ = -0.17  # b behind a, back to back: ~3 cm overlap (buttocks, heels, shoulder blades)


@pytest.fixture(scope="module")
def bodies(body_model):
    pose = torch.zeros(2, body_model.num_bones, 3)
    pose[1, 0, 1] = math.pi
    with torch.no_grad():
        v = body_model.forward(pose, None, torch.tensor([[0.0, 0.95, 0.0], [0.0, 0.95, 0.0]])).vertices
    faces = body_model.faces.cpu().numpy()
    fs = faces[collision_faces(faces, body_model.num_vertices)]
    return {"a": v[:1].clone(), "b": v[1:].clone(), "faces": faces, "fs": fs}


@pytest.fixture(scope="module")
def ct(bodies):
    return CollisionTerm(bodies["faces"])


def place(bodies, dx=0.0, dz=0.0):
    return bodies["a"], bodies["b"] + torch.tensor([float(dx), 0.0, float(dz)])


def reference(a, b, fs):
    """Independent depths on the body surface: igl.signed_distance with the winding-number sign."""
    A, B = a[0].double().numpy(), b[0].double().numpy()
    surf = np.zeros(len(A), bool)
    surf[np.unique(fs)] = True
    wn = igl.SIGNED_DISTANCE_TYPE_WINDING_NUMBER
    da = np.maximum(-igl.signed_distance(A, B, fs, wn)[0], 0.0) * surf
    db = np.maximum(-igl.signed_distance(B, A, fs, wn)[0], 0.0) * surf
    return da, db


def test_far_apart_costs_nothing(ct, bodies):
    a, b = place(bodies, dx=2.0)
    va, vb = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
    r = ct(va, vb)
    assert r.loss.shape == (1,) and r.loss.item() == 0.0
    assert not bool(r.active[0]) and r.penetrating.item() == 0 and r.max_depth_m.item() == 0.0
    assert ct.last_stats == {}  # no query at all
    r.loss.sum().backward()
    assert torch.count_nonzero(va.grad) == 0 and torch.count_nonzero(vb.grad) == 0
    p = ct.penetration(a, b)
    assert p["max_depth_m"].tolist() == [0.0] and p["share"].tolist() == [0.0]
    assert not p["depth_a"].any() and not p["depth_b"].any()


def test_known_overlap_matches_igl(ct, bodies):
    a, b = place(bodies, dz=HUG_DZ)
    da, db = reference(a, b, bodies["fs"])
    p = ct.penetration(a, b)
    V = a.shape[1]
    assert p["depth_a"].shape == (1, V) and p["depth_b"].shape == (1, V)
    ref_max = max(da.max(), db.max())
    assert 0.05 < ref_max < 0.15
    assert abs(p["max_depth_m"][0] - ref_max) < 5e-4
    assert np.abs(p["depth_a"][0] - da).max() < 5e-4 and np.abs(p["depth_b"][0] - db).max() < 5e-4
    missed = np.sum((da > 1e-4) & (p["depth_a"][0] == 0)) + np.sum((db > 1e-4) & (p["depth_b"][0] == 0))
    assert missed == 0
    n_ref = int(np.sum(da > ct.eps) + np.sum(db > ct.eps))
    assert p["penetrating"][0] == n_ref and p["share"][0] == pytest.approx(n_ref / (2 * V)) and p["share"][0] > 0.1
    r = ct(a, b)  # the loss path reports the same diagnostics
    assert bool(r.active[0]) and r.loss.item() > 0
    assert r.max_depth_m.item() == pytest.approx(p["max_depth_m"][0], abs=1e-6)
    assert r.penetrating.item() == p["penetrating"][0]
    # only vertices inside the other body's grown box were queried
    surf = np.zeros(V, bool)
    surf[np.unique(bodies["fs"])] = True
    A, B = a[0].numpy(), b[0].numpy()
    inbox = 0
    for q, o in ((B, A), (A, B)):
        lo, hi = o[surf].min(0) - ct.pad, o[surf].max(0) + ct.pad
        inbox += int(np.sum(np.all((q >= lo) & (q <= hi), axis=1) & surf))
    assert ct.last_stats["candidates"] == inbox < 2 * surf.sum()


def test_igl_and_winding_sign_agree_with_default(bodies):
    a, b = place(bodies, dz=HUG_DZ)
    pw = CollisionTerm(bodies["faces"]).penetration(a, b)
    for other in (CollisionTerm(bodies["faces"], method="igl"), CollisionTerm(bodies["faces"], sign="winding")):
        po = other.penetration(a, b)
        assert np.abs(pw["depth_a"] - po["depth_a"]).max() < 1e-5
        assert np.abs(pw["depth_b"] - po["depth_b"]).max() < 1e-5


def test_descent_on_translations_separates_both(ct, bodies):
    a, b = place(bodies, dz=BACK_DZ)
    assert ct.penetration(a, b)["max_depth_m"][0] > 0.02
    ta = torch.zeros(1, 3, requires_grad=True)
    tb = torch.zeros(1, 3, requires_grad=True)
    opt = torch.optim.Adam([ta, tb], lr=0.002)
    losses = []
    for _ in range(40):
        opt.zero_grad()
        r = ct(a + ta[:, None], b + tb[:, None])
        losses.append(r.loss.item())
        if r.max_depth_m.item() < 1e-3:
            break
        r.loss.sum().backward()
        opt.step()
    final = ct.penetration(a + ta.detach()[:, None], b + tb.detach()[:, None])
    assert final["max_depth_m"][0] < 1e-3
    assert losses[-1] < 0.01 * losses[0]
    # both bodies moved, apart along Z (b is behind a)
    assert ta[0, 2].item() > 0.003 and tb[0, 2].item() < -0.003


def test_gradient_matches_finite_differences(bodies):
    ct64 = CollisionTerm(bodies["faces"])
    a, b = place(bodies, dz=BACK_DZ)
    a, b = a.double(), b.double()
    ta = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    tb = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    r = ct64(a + ta[:, None], b + tb[:, None])
    r.loss.sum().backward()
    g = tb.grad[0].numpy()
    assert np.allclose(ta.grad[0].numpy(), -g, atol=1e-9)  # equal and opposite: both pushed apart
    assert g[2] > 0  # descent moves b further behind a
    # h: large enough to drown the float32 closest-point noise (~1e-10 in the loss), small enough
    # that the few vertices entering or leaving contact add nothing measurable
    h = 2e-4
    for axis in (0, 1, 2):
        e = torch.zeros(1, 1, 3, dtype=torch.float64)
        e[..., axis] = h
        fd = (ct64(a, b + e).loss.item() - ct64(a, b - e).loss.item()) / (2 * h)
        assert fd == pytest.approx(g[axis], rel=1e-2, abs=1e-3 * abs(g[2]))


def test_identical_position_is_pushed_apart(ct, bodies):
    a = bodies["a"]
    ta = torch.zeros(1, 3, requires_grad=True)
    tb = torch.zeros(1, 3, requires_grad=True)
    r = ct(a + ta[:, None], a + tb[:, None])
    # coincident surfaces: no vertex is inside the other, so the depths alone give nothing
    assert r.penetrating.item() == 0 and r.max_depth_m.item() == 0.0
    bare = CollisionTerm(bodies["faces"], guard_weight=0.0)(a + ta[:, None], a + tb[:, None]).loss
    assert bare.item() < 1e-6  # Jiang's pitfall without the guard
    assert r.loss.item() == pytest.approx(1.0)  # the guard, at full weight
    r.loss.sum().backward()
    assert ta.grad.norm() > 1.0 and torch.allclose(ta.grad, -tb.grad)
    step = 0.01
    with torch.no_grad():
        ta2, tb2 = ta - step * ta.grad, tb - step * tb.grad
    assert (tb2 - ta2).norm().item() > 0.1  # one step separates them
    assert ct(a + ta2[:, None], a + tb2[:, None]).loss.item() < r.loss.item()


@pytest.mark.slow
def test_guard_compares_the_torsos_so_a_close_hug_pays_nothing(body_model, bodies):
    """The simulated hug of seed 2 brings the whole bodies' centroids within 10 cm (arms wrapped round
    the partner) while the torsos stay ~25 cm apart: the whole-body guard fires there and pushes the
    bodies apart against the data; the torso guard the fitter uses does not, and still separates
    coincident bodies."""
    from dualhuman_builder.fit.skeleton import torso_vertices
    from dualhuman_builder.sim.scenes import SceneParams, make_scene

    torso = torso_vertices(body_model)
    bones = np.asarray(body_model.bone_names)[body_model.vertex_bone()[torso]]
    assert 1000 < len(torso) < 2000 and all(b.startswith(("root", "pelvis", "spine")) for b in bones)
    a, b = make_scene(SceneParams(type="hug", seed=2, fps=5)).sequence.actors
    va, vb = torch.tensor(a.vertices()), torch.tensor(b.vertices())
    whole = (vb.mean(1) - va.mean(1)).norm(dim=1)
    core = (vb[:, torso].mean(1) - va[:, torso].mean(1)).norm(dim=1)
    close = torch.nonzero(whole < 0.1).flatten()
    assert len(close) >= 3 and core.min() > 0.2
    va, vb = va[close], vb[close]
    faces = bodies["faces"]
    bare = CollisionTerm(faces, guard_weight=0.0)(va, vb).loss
    assert torch.allclose(CollisionTerm(faces, guard_vertices=torso)(va, vb).loss, bare)
    assert (CollisionTerm(faces)(va, vb).loss - bare > 0.05).all()  # the whole-body guard fires
    # coincident bodies: the torso guard pays in full and pushes them apart
    t = torch.zeros(1, 3, requires_grad=True)
    r = CollisionTerm(faces, guard_vertices=torso)(bodies["a"], bodies["a"] + t[:, None])
    assert r.loss.item() == pytest.approx(1.0)
    r.loss.sum().backward()
    assert t.grad[0, 0] < -1.0  # descent moves b along +X
    with pytest.raises(ValueError, match="guard_vertices"):
        CollisionTerm(faces, guard_vertices=[])
    with pytest.raises(ValueError, match="out of range"):
        CollisionTerm(faces, guard_vertices=[10**6])(bodies["a"], bodies["a"])


def test_thin_penetration_is_seen(ct, bodies):
    # back to back, shifted until the deepest point is ~3 mm inside (depth moves ~1:1 with the shift)
    dz = BACK_DZ
    for _ in range(2):
        da, db = reference(*place(bodies, dz=dz), bodies["fs"])
        dz -= float(max(da.max(), db.max())) - 0.003
    a, b = place(bodies, dz=dz)
    da, db = reference(a, b, bodies["fs"])
    ref = max(da.max(), db.max())
    assert 0.002 < ref < 0.004
    p = ct.penetration(a, b)
    assert abs(p["max_depth_m"][0] - ref) < 5e-4 and p["penetrating"][0] > 0
    # Jiang's 32^3 grid has cells of several centimetres: it cannot measure this
    pg = CollisionTerm(bodies["faces"], method="grid").penetration(a, b)
    err = max(np.abs(pg["depth_a"][0] - da).max(), np.abs(pg["depth_b"][0] - db).max())
    assert err > 5e-4


def test_batch_equals_frames_one_by_one(ct, bodies):
    a = bodies["a"]
    bs = [place(bodies, dz=HUG_DZ)[1], place(bodies, dx=2.0)[1], place(bodies, dz=BACK_DZ)[1], a]
    A = torch.cat([a] * 4).requires_grad_(True)
    B = torch.cat(bs).requires_grad_(True)
    r = ct(A, B)
    assert r.loss.shape == (4,) and r.active.tolist() == [True, False, True, True]
    r.loss.sum().backward()
    for i in range(4):
        va = a.clone().requires_grad_(True)
        vb = bs[i].clone().requires_grad_(True)
        s = ct(va, vb)
        assert s.loss.item() == pytest.approx(r.loss[i].item(), rel=1e-5, abs=1e-9)
        assert s.penetrating.item() == r.penetrating[i].item()
        assert s.max_depth_m.item() == pytest.approx(r.max_depth_m[i].item(), abs=1e-7)
        s.loss.sum().backward()
        assert torch.allclose(va.grad, A.grad[i : i + 1], atol=1e-7)
        assert torch.allclose(vb.grad, B.grad[i : i + 1], atol=1e-7)
    assert r.loss[1].item() == 0.0


def test_points_give_the_dense_loss_and_gradient(ct, bodies):
    """``points=``: the loss reads positions at the pairs it needs from a callable (the fitter skins
    just those); loss, diagnostics and gradient equal the dense call's, on overlapping, far,
    shallow and coincident frames (the last through the guard, which reads whole frames)."""
    a = bodies["a"]
    bs = [place(bodies, dz=HUG_DZ)[1], place(bodies, dx=2.0)[1], place(bodies, dz=BACK_DZ)[1], a]
    A, B = torch.cat([a] * 4).double(), torch.cat(bs).double()  # float64: summation order does not show
    grads, results, read = [], [], []
    for sparse in (False, True):
        ta = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
        tb = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
        if sparse:
            def points(body, f, v, shift=(ta, tb)):
                read.append((body, len(f)))
                return (A, B)[body][f, v] + shift[body][f]

            r = ct((A + ta[:, None]).detach(), (B + tb[:, None]).detach(), points=points)
        else:
            r = ct(A + ta[:, None], B + tb[:, None])
        r.loss.sum().backward()
        results.append(r)
        grads.append((ta.grad.clone(), tb.grad.clone()))
    dense, sparse = results
    assert torch.allclose(dense.loss, sparse.loss, rtol=1e-12, atol=0) and dense.loss[0] > 0 and dense.loss[2] > 0
    assert torch.equal(dense.penetrating, sparse.penetrating) and torch.equal(dense.max_depth_m, sparse.max_depth_m)
    for g_dense, g_sparse in zip(*grads):
        assert torch.allclose(g_dense, g_sparse, rtol=1e-10, atol=1e-14)
    assert grads[0][0][1].abs().max() == 0.0 and grads[0][0][0].abs().max() > 0  # far: nothing; hug: pushed
    V = A.shape[1]
    guarded = int(((B.mean(dim=1) - A.mean(dim=1)).norm(dim=1) < ct.guard_m).sum())  # coincident and hug
    assert guarded == 2 and read[2:] == [(0, guarded * V), (1, guarded * V)]  # the guard reads those frames whole
    assert 0 < read[0][1] + read[1][1] < 0.5 * 2 * 4 * V  # the contacts: a fraction of the vertices
    with pytest.raises(ValueError, match="exact method"):
        CollisionTerm(bodies["faces"], method="grid")(A, B, points=points)


def test_linearised_term_equals_the_exact_one_where_located_and_follows_small_moves(bodies):
    """``linearise`` locates the contacts once; ``linear_loss`` re-reads only their positions. At the
    located bodies it gives the exact term's loss and gradient (both translations; hug, far, back to
    back, coincident frames) and ``penetration``'s diagnostics. After b moves 3 mm toward a, the held
    planes still give the exact loss to within 5 %, and vertices that were outside within the margin
    and crossed in are counted: without the margin the loss falls short."""
    ct = CollisionTerm(bodies["faces"], band_m=0.01)
    a = bodies["a"]
    bs = [place(bodies, dz=HUG_DZ)[1], place(bodies, dx=2.0)[1], place(bodies, dz=BACK_DZ)[1], a]
    A, B = torch.cat([a] * 4).double(), torch.cat(bs).double()

    def loss_and_grad(fn, B_now):
        ta = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
        tb = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)

        def points(body, f, v):
            return (A, B_now)[body][f, v] + (ta, tb)[body][f]

        loss = fn(points)
        loss.sum().backward()
        return loss.detach(), ta.grad, tb.grad

    lin = ct.linearise(A, B, margin_m=0.005)
    exact = loss_and_grad(lambda pts: ct(A.detach(), B.detach(), points=pts).loss, B)
    held = loss_and_grad(lambda pts: ct.linear_loss(lin, pts, dtype=torch.float64), B)
    for x, y in zip(exact, held):
        assert torch.allclose(x, y, rtol=1e-9, atol=1e-14)
    assert exact[0][0] > 0 and exact[0][1] == 0 and exact[0][2] > 0
    pen = ct.penetration(A, B)
    assert np.array_equal(lin.penetrating, pen["penetrating"]) and np.allclose(lin.max_depth_m, pen["max_depth_m"])
    assert np.array_equal(lin.active, pen["active"]) and lin.guard.tolist() == [0, 3]
    c = lin.contacts
    outside = c.depth < 0
    assert outside.any() and c.depth[outside].min() >= -0.005  # the margin's vertices, held for later
    assert np.allclose(np.linalg.norm(lin.normals, axis=1), 1.0)

    # after a move: the back-to-back frame (b moves 3 mm into a), and back to back 3.5 cm farther apart
    # (2.7 mm apart: nothing inside; b moves 5 mm into a). The held planes against the exact term
    B2 = B.clone()
    B2[2] += torch.tensor([0.0, 0.0, 0.003], dtype=torch.float64)
    exact2 = ct(A, B2).loss[2].item()
    held2 = loss_and_grad(lambda pts: ct.linear_loss(lin, pts, dtype=torch.float64), B2)[0][2].item()
    assert exact2 > 1.15 * exact[0][2].item() and held2 == pytest.approx(exact2, rel=0.02)
    a1, b1 = (x.double() for x in place(bodies, dz=BACK_DZ - 0.035))
    assert ct.penetration(a1, b1)["penetrating"][0] == 0
    b1_moved = b1 + torch.tensor([0.0, 0.0, 0.005], dtype=torch.float64)
    exact3 = ct(a1, b1_moved).loss.item()
    held3, zero3 = (ct.linear_loss(ct.linearise(a1, b1, margin_m=m), lambda body, f, v: (a1, b1_moved)[body][f, v],
                                   dtype=torch.float64).item() for m in (0.005, 1e-9))  # fmt: skip
    assert exact3 > 0 and held3 == pytest.approx(exact3, rel=0.1) and zero3 == 0.0
    # a subset of the frames: the same terms, renumbered
    sub = lin.subset([2, 0])
    sub_loss = loss_and_grad(lambda pts: ct.linear_loss(lin, pts, dtype=torch.float64), B)[0]
    both = ct.linear_loss(sub, lambda body, f, v: (A, B)[body][torch.tensor([2, 0])[f], v], dtype=torch.float64)
    assert torch.allclose(both, sub_loss[[2, 0]], rtol=1e-12) and sub.B == 2 and sub.guard.tolist() == [1]
    assert ct.linear_loss(lin.subset([3]), lambda body, f, v: (A, B)[body][3 + f, v], dtype=torch.float64).item() > 0
    with pytest.raises(ValueError, match="distinct rows"):
        lin.subset([0, 0])
    with pytest.raises(ValueError, match="margin_m"):
        ct.linearise(A, B, margin_m=0.02)
    with pytest.raises(ValueError, match="exact method"):
        CollisionTerm(bodies["faces"], method="grid").linearise(A, B)


def test_flood_fill_does_not_guess_across_a_sign_conflict(body_model, bodies):
    """Bodies posed with 0.3 rad of noise on every joint cross themselves (arms through the torso),
    where the pseudonormal sign can be wrong. A flood-fill component then holds members known inside
    and members known outside; its open members get a query each instead of the sign of any one
    member, which keeps the vertices on the wrong side of the winding number few."""
    g = torch.Generator().manual_seed(6)
    pose = torch.randn(2, body_model.num_bones, 3, generator=g) * 0.3
    pose[:, 0] = 0.0
    pose[1, 0, 1] = math.pi
    with torch.no_grad():
        v = body_model.forward(pose, None, torch.tensor([[0.0, 0.95, 0.0], [0.0, 0.95, 0.15]])).vertices
    ct = CollisionTerm(bodies["faces"])
    p = ct.penetration(v[:1], v[1:])
    assert ct.last_stats["conflicted"] > 100
    da, db = reference(v[:1], v[1:], bodies["fs"])
    wrong = ((p["depth_a"][0] > 1e-5) != (da > 1e-5)).sum() + ((p["depth_b"][0] > 1e-5) != (db > 1e-5)).sum()
    assert wrong < 200 and (da > 1e-5).sum() + (db > 1e-5).sum() > 1000
    assert p["max_depth_m"][0] == pytest.approx(max(da.max(), db.max()), abs=1e-6)


def test_keys_reuse_signs_and_give_the_same_answer(bodies):
    """Calls naming their frames reuse the last call's signs where the bodies moved too little to
    change them; every answer equals a fresh term's, through small moves (reuse) and large ones
    (vertices crossing the surface, a body pushed 5 cm deeper)."""
    fresh = CollisionTerm(bodies["faces"])
    kept = CollisionTerm(bodies["faces"])
    a = bodies["a"]
    rng = np.random.default_rng(0)
    moves = [0.0, 0.0005, 0.001, -0.002, 0.0, -0.05, -0.048, 0.06]  # metres along Z, both frames
    reused = []
    for step, dz in enumerate(moves):
        b = torch.cat([place(bodies, dz=HUG_DZ + dz)[1], place(bodies, dz=BACK_DZ - dz)[1]])
        b = b + torch.as_tensor(rng.normal(0, 2e-4, b.shape), dtype=b.dtype)  # every vertex moves
        A = torch.cat([a, a])
        pf = fresh.penetration(A, b)
        pk = kept.penetration(A, b, keys=[7, 8])
        for k in ("depth_a", "depth_b"):
            assert np.abs(pf[k] - pk[k]).max() < 1e-6, (step, k)
        assert pk["penetrating"].tolist() == pf["penetrating"].tolist()
        assert pf["penetrating"][0] > 0  # the hug always overlaps; back to back parts at the last move
        reused.append(kept.last_stats["reused"] / kept.last_stats["candidates"])
        va, vb = A.clone().requires_grad_(True), b.clone().requires_grad_(True)
        rk = kept(va, vb, keys=np.array([7, 8]))
        rk.loss.sum().backward()
        wa, wb = A.clone().requires_grad_(True), b.clone().requires_grad_(True)
        rf = fresh(wa, wb)
        rf.loss.sum().backward()
        assert torch.allclose(rk.loss, rf.loss, rtol=1e-6, atol=1e-12)
        assert torch.allclose(va.grad, wa.grad, atol=1e-9) and torch.allclose(vb.grad, wb.grad, atol=1e-9)
    assert reused[0] == 0.0  # nothing remembered yet
    # small moves: most signs carried over (bounds shrink by each move until a vertex is asked again)
    assert reused[1] > 0.9 and min(reused[1:5]) > 0.5
    assert reused[5] < reused[4]  # 5 cm deeper: many vertices had to be asked again
    with pytest.raises(ValueError, match="name each of the 2 frames"):
        kept.penetration(A, b, keys=[1])
    with pytest.raises(ValueError, match="distinct"):
        kept(A, b, keys=[3, 3])
    small = CollisionTerm(bodies["faces"], max_memo=1)
    small.penetration(A, b, keys=["x", "y"])
    assert len(small.memory) == 1
    kept.clear_memo()
    assert len(kept.memory) == 0


def test_rho_keeps_pushing_deep_vertices(bodies):
    d = torch.tensor([0.001, 0.05], requires_grad=True)
    for name in ("pseudo_huber", "squared", "geman_mcclure"):
        d.grad = None
        CollisionTerm(bodies["faces"], rho=name).rho(d).sum().backward()
        slope_deep = d.grad[1].item()
        if name == "geman_mcclure":
            assert slope_deep < 2.0  # saturated: 2 s^2 / d^3 ~ 1.6 per metre, vs 65 at its peak
        else:
            assert slope_deep >= 0.98 / 0.01  # pseudo-Huber ~1/s, squared 2 d / s^2


def test_bad_input(ct, bodies):
    a = bodies["a"]
    with pytest.raises(ValueError, match="same shape"):
        ct(a, torch.cat([a, a]))
    with pytest.raises(ValueError, match=r"\(B, V, 3\)"):
        ct(a[..., :2], a[..., :2])
    bad = a.clone()
    bad[0, 10, 1] = float("nan")
    with pytest.raises(ValueError, match="verts_b contains NaN"):
        ct(a, bad)
    with pytest.raises(ValueError, match="verts_a contains NaN"):
        ct.penetration(bad, a)
    with pytest.raises(ValueError, match="empty"):
        ct(a[:0], a[:0])
    with pytest.raises(ValueError, match="faces index up to"):
        ct(a[:, :100], a[:, :100])
    with pytest.raises(ValueError, match="torch tensor"):
        ct(a.numpy(), a.numpy())
    with pytest.raises(ValueError, match="method must be one of"):
        CollisionTerm(bodies["faces"], method="bvh")
    with pytest.raises(ValueError, match="not closed"):
        CollisionTerm(bodies["faces"][:-1])
    with pytest.raises(ValueError, match=r"faces must have shape \(F, 3\)"):
        CollisionTerm(np.zeros((0, 3), int))
    with pytest.raises(ValueError, match="band_m must be a positive"):
        CollisionTerm(bodies["faces"], band_m=0.0)


def test_flood_fill_components_are_those_of_the_edges_an_unknown_sign_cannot_cross(bodies):
    """The flood fill's union-find (warp kernels) against scipy's connected components over the
    edges the rule allows: an end of unknown sign, and the ends' distance bounds adding up to more
    than the edge (a margin for float32 rounding). Per vertex of unknown sign: its component's known
    sign (written into the signs), a conflict (members known on both sides), or, without a known
    member, the component's first vertex (its representative) and the others pointing at it."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ct = CollisionTerm(bodies["faces"])
    V = bodies["a"].shape[1]
    P = 3
    rng = np.random.default_rng(5)
    pts = (bodies["a"][0].numpy()[None] + rng.normal(0, 0.002, (P, V, 3))).astype(np.float32)
    bound = rng.uniform(0.0, 0.02, (P, V)).astype(np.float32)
    sgn = rng.choice(np.array([-1, 0, 1], np.int8), size=(P, V), p=[0.1, 0.6, 0.3])
    rows = np.array([0, 2])  # problem 1 has nothing to fill
    before = sgn.copy()
    code = ct.locator.flood(pts, bound, sgn, rows)
    assert code.shape == (2, V)
    np.testing.assert_array_equal(sgn[1], before[1])
    e0, e1 = ct.edges[:, 0], ct.edges[:, 1]
    counts = np.zeros(4, int)
    for t, p in enumerate(rows):
        length = np.linalg.norm(pts[p, e0].astype(np.float64) - pts[p, e1], axis=1)
        total = bound[p, e0].astype(np.float64) + bound[p, e1]
        limit = length * (1 + 1e-4) + 1e-6
        assert not (np.abs(total - limit) < 1e-6 * total).any()  # no edge that float32 rounding could decide
        ok = ((before[p, e0] == 0) | (before[p, e1] == 0)) & (total > limit)
        _, comp = connected_components(coo_matrix((np.ones(ok.sum()), (e0[ok], e1[ok])), shape=(V, V)), directed=False)
        pos = np.zeros(V, bool)
        neg = np.zeros(V, bool)
        pos[comp[before[p] > 0]] = True
        neg[comp[before[p] < 0]] = True
        first = np.full(V, -1)
        for v in range(V):
            if first[comp[v]] < 0:
                first[comp[v]] = v
        c = comp
        want = np.select([before[p] != 0, pos[c] & neg[c], pos[c], neg[c], first[c] == np.arange(V)], [0, 2, 1, -1, 3], -(4 + first[c]))
        agreed = np.abs(want) == 1  # written into the signs; the code says what the others need
        np.testing.assert_array_equal(sgn[p], np.where(agreed, want, before[p]))
        np.testing.assert_array_equal(code[t], np.where(agreed, 0, want))
        counts += [(want == k).sum() for k in (1, -1, 2, 3)]
    assert (counts > 50).all(), counts  # every kind of answer occurs


def _finger_groups(body_model) -> np.ndarray:
    """``(V,)`` 1 for vertices skinned mostly to the left hand's fingers, 2 the right's, 0 the rest."""
    names = body_model.bone_names
    bone = body_model.vertex_bone()
    return np.array([1 + ("RL".find(names[b][-1]) == 0) if names[b].startswith("finger") else 0 for b in bone])


def test_contacts_only_the_moving_vertices_change_give_the_same_gradient(bodies, body_model):
    """``moving_only`` keeps the located contacts that a move of some vertices can change (their query
    vertex or a corner of their triangle moves): the held loss then differs by a constant, with the same
    gradient, when only those vertices move."""
    ct = CollisionTerm(bodies["faces"])
    a, b = (x.double() for x in place(bodies, dz=HUG_DZ))
    lin = ct.linearise(a, b, margin_m=0.005)
    V = a.shape[1]
    moving = a[0, :, 0].numpy() > 0.05  # one side of the body (either body: the same vertex indices)
    sub = ct.moving_only(lin, moving)
    c = lin.contacts
    n_kept = len(sub.contacts.frame)
    assert 0 < n_kept < len(c.frame)
    # a kept contact touches a moving vertex; a dropped one does not
    touch = moving[c.vert] | moving[ct.obstacle_faces[c.face]].any(axis=1)
    assert n_kept == int(touch.sum()) and np.array_equal(sub.contacts.vert, c.vert[touch])
    mask = torch.as_tensor(moving, dtype=torch.float64)[:, None]

    def loss_and_grad(term, shift):
        t = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
        loss = ct.linear_loss(term, lambda body, f, v: (a, b)[body][f, v] + (t[body] + shift[body]) * mask[v],
                              dtype=torch.float64)  # fmt: skip
        loss.sum().backward()
        return loss.detach(), t.grad

    for shift in (torch.zeros(2, 3, dtype=torch.float64), torch.tensor([[0.0, 0.0, 0.004], [0.003, -0.002, 0.0]], dtype=torch.float64)):
        (lf, gf), (ls, gs) = loss_and_grad(lin, shift), loss_and_grad(sub, shift)
        assert gf.abs().max() > 0 and torch.allclose(gf, gs, rtol=1e-9, atol=1e-15)
        if shift.any():
            assert torch.allclose(lf - ls, gap, rtol=1e-9, atol=1e-15)  # the dropped contacts' share did not change
        gap = lf - ls
    assert gap.item() > 0
    with pytest.raises(ValueError, match="moving must be"):
        ct.moving_only(lin, moving[:-1])


@pytest.mark.slow
def test_signs_are_kept_away_from_the_parts_that_moved_far(bodies, body_model):
    """With ``parts`` (here: the fingers of each hand, and the rest), a call after the fingers moved 3 cm
    keeps the remembered signs of the vertices far from them, where the plain bound (the obstacle's
    largest move) keeps few: fewer queries, the same answer as a fresh call. So it does when the rest
    moved a millimetre too (each part's own move bounds it), and then every vertex 1 mm again."""
    groups = _finger_groups(body_model)
    fingers = torch.as_tensor(groups > 0)
    a, b = place(bodies, dz=HUG_DZ)
    # every term's meshes are built over the same points (which of two equally close faces a query returns
    # depends on the tree a build made)
    same = {"band_m": 0.03, "bvh_points": a[0].numpy()}
    down = torch.where(fingers[:, None], torch.tensor([0.0, -0.03, 0.0]), torch.zeros(3))
    for rest in (torch.zeros(3), torch.tensor([0.001, 0.0, 0.0])):
        # every finger vertex 3 cm down, the rest still or 1 mm to the side
        a2, b2 = (x + down + torch.where(fingers[:, None], torch.zeros(3), rest) for x in (a, b))
        fresh = CollisionTerm(bodies["faces"], **same).linearise(a2, b2, margin_m=0.005)
        reused = {}
        for name, parts in (("plain", None), ("parts", groups)):
            ct = CollisionTerm(bodies["faces"], parts=parts, **same)
            assert ct.num_parts == (1 if parts is None else 3)
            ct.linearise(a, b, keys=[7], margin_m=0.005)
            lin = ct.linearise(a2, b2, keys=[7], margin_m=0.005)
            reused[name] = ct.last_stats["reused"]
            for f in ("frame", "side", "vert", "face"):
                assert np.array_equal(getattr(lin.contacts, f), getattr(fresh.contacts, f))
            assert np.allclose(lin.contacts.depth, fresh.contacts.depth, atol=1e-7)
            assert np.array_equal(lin.penetrating, fresh.penetrating)
            # then everything moves 1 mm: the same answer as a fresh call
            a3, b3 = a2 + 0.001, b2 - 0.001
            lin3 = ct.linearise(a3, b3, keys=[7], margin_m=0.005)
            fresh3 = CollisionTerm(bodies["faces"], **same).linearise(a3, b3, margin_m=0.005)
            assert np.array_equal(lin3.contacts.vert, fresh3.contacts.vert) and np.array_equal(lin3.penetrating, fresh3.penetrating)
        assert fresh.penetrating[0] > 0
        assert reused["parts"] > 5 * reused["plain"] and reused["parts"] > 15000, reused
    with pytest.raises(ValueError, match="parts"):
        CollisionTerm(bodies["faces"], parts=groups[:100])


def test_frames_never_seen_start_from_their_neighbours_signs(bodies):
    """With ``seed_stride`` (4 by default) a call naming frames it has never seen finds every fourth
    first, then the others from the signs of the one before them: the same contacts as finding each
    alone (``seed_stride=1``), with most signs carried over instead of asked again."""
    steps = np.arange(9) * 0.002  # b walks into a, 2 mm a frame
    b = torch.cat([place(bodies, dz=HUG_DZ - dz)[1] for dz in steps])
    a = bodies["a"].expand(len(steps), -1, -1).contiguous()
    same = {"band_m": 0.03, "bvh_points": bodies["a"][0].numpy()}
    out = {}
    for stride in (1, 4):
        ct = CollisionTerm(bodies["faces"], seed_stride=stride, **same)
        assert [list(r) for r, _ in ct.memory.levels(list(range(9)), a.shape[1])] == (
            [list(range(9))] if stride == 1 else [[0, 4, 8], [2, 6], [1, 3, 5, 7]])
        out[stride] = (ct.linearise(a, b, keys=range(9), margin_m=0.005), dict(ct.last_stats))
    (one, s1), (seeded, s4) = out[1], out[4]
    for f in ("frame", "side", "vert", "face"):
        assert np.array_equal(getattr(one.contacts, f), getattr(seeded.contacts, f))
    assert np.allclose(one.contacts.depth, seeded.contacts.depth, atol=1e-7)
    assert np.array_equal(one.penetrating, seeded.penetrating) and one.penetrating.min() > 0
    assert s1["reused"] == 0 and s4["reused"] > 0.5 * s4["candidates"], s4
    assert s4["near"] + s4["far"] < 0.8 * (s1["near"] + s1["far"])  # queries (the inside vertices still need their depth)
    with pytest.raises(ValueError, match="seed_stride"):
        CollisionTerm(bodies["faces"], seed_stride=3)
