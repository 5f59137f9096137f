"""Tests of the deployable latent runtime (latentsim.runtime).

The folded NumPy, compiled and torch.export runtimes must reproduce the PyTorch modules
(eval-mode BatchNorm with non-trivial statistics, trained for a few steps) in
both coordinate modes, survive a file round trip, step without allocating,
and the hand-written forward-mode Jvp must equal ``torch.func.jvp``.
"""

from __future__ import annotations

import copy
import importlib.util
import json
import re
import tracemalloc
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from latentsim import runtime as rt
from latentsim.latent import (
    Autoencoder,
    LatentIntegrator,
    RelativeCoordinates,
    decode_latents,
    encode_positions,
    rollout,
)
from latentsim.latent.timing import EagerStepper
from latentsim.runtime import compiled as rc
from latentsim.runtime import numpy_stepper

# torch.func.jvp (the Jvp oracle) scripts torch's own decompositions (torch._decomp.decompositions_for_jvp) with
# torch.jit at its first use, which warns; the project itself uses no torch.jit

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "step_trained_model.py"
K = 6  # boundary-condition parameters per frame
R = 3  # latent dimension


ONE_THREAD = True  # tiny networks (conftest)


def _coords(mode: str) -> RelativeCoordinates:
    n = 12
    if mode == "roots":  # two rods of 6 vertices, roots 0 and 6
        return RelativeCoordinates(n, [0, 6], "roots", root_of=[0] * 6 + [6] * 6)
    return RelativeCoordinates(n, [0, 1, 2], mode)  # mean, hard_mean


def _trained_modules(mode: str, seed: int = 0):
    """Autoencoder (widths with and without identity skips) and integrator,
    each trained a few Adam steps on random data so that BatchNorm running
    statistics, the zero-initialised branch outputs and the integrator's
    normalisation are all non-trivial."""
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    coords = _coords(mode)
    U = torch.randn(96, coords.dim, generator=g) * torch.linspace(0.2, 2.0, coords.dim) + 0.3
    ae = Autoencoder(coords.dim, R, [16, 16, 8], pca_dim=12)
    ae.init_pca(U)
    opt = torch.optim.Adam(ae.parameters(), lr=1e-2)
    for _ in range(8):
        ae.train()
        loss = ((ae(U) - U) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    ae.eval()
    integ = LatentIntegrator(R, K, [20, 24])
    Z = torch.randn(96, 3, R, generator=g)
    P = torch.randn(96, 3, K, generator=g) * 2.0 + 1.0
    integ.fit_normalization(Z[:, 0], Z[:, 1], Z[:, 2], P[:, 0], P[:, 1], P[:, 2])
    opt = torch.optim.Adam(integ.parameters(), lr=1e-2)
    for _ in range(8):
        loss = ((integ(Z[:, 1], Z[:, 2], P[:, 0], P[:, 1], P[:, 2]) - torch.sin(Z[:, 0])) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    integ.eval()
    assert ae.dec_branch.out.weight.abs().max() > 0  # the branch is no longer zero
    assert (ae.dec_branch.blocks[0][1].running_var - 1).abs().max() > 1e-3
    return ae, integ, coords


def _inputs(coords, seed=1, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    z1, z2 = (torch.randn(R, generator=g).to(dtype) for _ in range(2))
    p, p1, p2 = (torch.randn(K, generator=g).to(dtype) for _ in range(3))
    xD = torch.randn(coords.dirichlet.numel(), 3, generator=g, dtype=torch.float64)
    return z1, z2, p, p1, p2, xD


def _reference(ae, integ, coords, args):
    z1, z2, p, p1, p2, xD = args
    with torch.no_grad():
        z = integ(z1[None], z2[None], p[None], p1[None], p2[None])
        x = decode_latents(ae, coords, z, xD[None])
    return z[0].double().numpy(), x[0].numpy()


LAYOUTS = [("roots", "full"), ("roots", "scatter"), ("mean", "full"), ("hard_mean", "full"), ("hard_mean", "scatter")]


def _force_layout(monkeypatch, layout: str) -> None:
    """The hard modes decode over all vertices ("full") or scatter the free ones ("scatter")."""
    monkeypatch.setattr(numpy_stepper, "FULL_LAYOUT_MAX_GROWTH", np.inf if layout == "full" else 0.0)


@pytest.mark.parametrize(("mode", "layout"), LAYOUTS)
def test_runtimes_match_modules_float64(mode, layout, monkeypatch):
    _force_layout(monkeypatch, layout)
    ae, integ, coords = _trained_modules(mode)
    ae64, integ64 = copy.deepcopy(ae).double(), copy.deepcopy(integ).double()
    args = _inputs(coords, dtype=torch.float64)
    z_ref, x_ref = _reference(ae64, integ64, coords, args)
    folded = rt.fold_networks(ae, integ, coords)
    np_step = rt.NumpyStepper(folded, np.float64)
    assert np_step.layout == layout
    z, x = np_step.step(*(a.numpy() for a in args))
    with pytest.raises(ValueError, match="C-contiguous"):  # a strided out would be written as a copy
        np_step.decode(z, args[-1].numpy(), out=np.empty((coords.n, 6))[:, :3])
    assert np.allclose(z, z_ref, rtol=0, atol=1e-12)
    assert np.allclose(x, x_ref, rtol=0, atol=1e-12)
    zt, xt = rt.ExportedStepper(folded, torch.float64).step(*args)
    assert np.allclose(zt.numpy(), z_ref, rtol=0, atol=1e-12)
    assert np.allclose(xt.numpy(), x_ref, rtol=0, atol=1e-12)
    if mode != "mean":  # prescribed vertices re-applied exactly
        assert np.array_equal(x[coords.dirichlet.numpy()], args[-1].numpy())
        assert np.array_equal(xt.numpy()[coords.dirichlet.numpy()], args[-1].numpy())
    # the folding is not an identity: the decoded frame differs from plain PCA
    assert np.abs(x_ref).max() > 0.1


@pytest.mark.parametrize("pca_dim", [4, 24])
def test_narrow_and_wide_pca_layers(pca_dim):
    """A PCA layer narrower than the last hidden layer keeps the branch output layer apart
    (folding it would widen the largest matrix); a wide one folds it into W_cat."""
    coords = RelativeCoordinates(40, [0, 1, 2], "mean")
    torch.manual_seed(2)
    ae = Autoencoder(coords.dim, R, [16, 16], pca_dim=pca_dim)
    ae.init_pca(torch.randn(64, coords.dim))
    with torch.no_grad():
        ae.dec_branch.out.weight.normal_(0.0, 0.3)
    ae.eval()
    integ = LatentIntegrator(R, K, [8]).eval()
    folded = rt.fold_networks(ae, integ, coords)
    assert folded["header"]["decoder_mid"] == (pca_dim < 16)
    args = _inputs(coords, seed=11, dtype=torch.float64)
    z_ref, x_ref = _reference(copy.deepcopy(ae).double(), copy.deepcopy(integ).double(), coords, args)
    z, x = rt.NumpyStepper(folded, np.float64).step(*(a.numpy() for a in args))
    zt, xt = rt.ExportedStepper(folded, torch.float64).step(*args)
    for a, b in ((z, z_ref), (x, x_ref), (zt.numpy(), z_ref), (xt.numpy(), x_ref)):
        assert np.allclose(a, b, rtol=0, atol=1e-12)
    st = rt.NumpyStepper(folded, np.float64)
    v = np.ones(R)
    du_ref = rt.jvp_vertex_torch(copy.deepcopy(ae).double(), args[0], torch.from_numpy(v), 7)[1]
    assert np.allclose(st.jvp_vertex(args[0].numpy(), v, 7)[1], du_ref.detach().numpy(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("mode", ["roots", "mean", "hard_mean"])
def test_runtimes_match_modules_float32(mode):
    ae, integ, coords = _trained_modules(mode, seed=3)
    args = _inputs(coords, seed=4)
    z_ref, x_ref = _reference(ae, integ, coords, args)
    folded = rt.fold_networks(ae, integ, coords)
    z, x = rt.NumpyStepper(folded, np.float32).step(*(a.numpy() for a in args))
    assert z.dtype == np.float32 and x.dtype == np.float64
    scale = np.abs(x_ref).max()
    assert np.allclose(z, z_ref, rtol=1e-5, atol=1e-5)
    assert np.abs(x - x_ref).max() < 1e-5 * scale
    zt, xt = rt.ExportedStepper(folded, torch.float32).step(*args)
    assert np.allclose(zt.numpy(), z_ref, rtol=1e-5, atol=1e-5)
    assert np.abs(xt.numpy() - x_ref).max() < 1e-5 * scale


@pytest.mark.parametrize("mode", ["roots", "mean", "hard_mean"])
def test_export_load_round_trip_and_rollout(mode, tmp_path):
    ae, integ, coords = _trained_modules(mode, seed=5)
    T = 12
    g = torch.Generator().manual_seed(6)
    bc = torch.randn(T, K, generator=g)
    xD = torch.randn(T, coords.dirichlet.numel(), 3, generator=g, dtype=torch.float64)
    z0, z1 = torch.randn(R, generator=g), torch.randn(R, generator=g)
    ref = rollout(integ, ae, coords, z0, z1, bc, xD)
    assert ref["diverged_frame"] == -1
    scale = float(ref["positions"].abs().max())
    for name in ("runtime.npz", "runtime.pt2"):
        rt.export_runtime(ae, integ, coords, tmp_path / name)
        if name.endswith(".npz"):
            out = rt.rollout_runtime(rt.load_runtime(tmp_path / name), z0.numpy(), z1.numpy(), bc.numpy(), xD.numpy())
            Z, X = out["latents"], out["positions"]
        else:  # the exported step runs with torch.export.load alone
            with pytest.raises(ValueError, match="torch.export.load"):
                rt.load_runtime(tmp_path / name)
            step = torch.export.load(str(tmp_path / name)).module()
            Zl, Xl = [z0, z1], []
            for t in range(2, T):
                z, x = step(Zl[-1], Zl[-2], bc[t], bc[t - 1], bc[t - 2], xD[t])
                Zl.append(z)
                Xl.append(x)
            Z, X = torch.stack(Zl).numpy(), np.concatenate([ref["positions"][:2].numpy(), torch.stack(Xl).numpy()])
        # float32 networks, 10 autoregressive steps: round-off only
        assert np.abs(Z - ref["latents"].numpy()).max() < 1e-4
        assert np.abs(X - ref["positions"].numpy()).max() < 1e-4 * scale
    with pytest.raises(ValueError, match="npz"):
        rt.export_runtime(ae, integ, coords, tmp_path / "runtime.bin")


def test_a_checked_program_takes_float64_and_a_damaged_one_is_named_and_moved_aside(tmp_path, monkeypatch):
    """runtime.pt carries the checksum of its weights: load_program steps it on float64 inputs (as h5py gives
    them) exactly as the raw program on its own dtypes; a flipped weight byte or a truncated file is named and
    moved aside; a write that fails leaves no temporary file."""
    from latentsim.checksum import ArtefactError

    ae, integ, coords = _trained_modules("mean", seed=5)
    path = tmp_path / "runtime.pt"
    rt.export_runtime(ae, integ, coords, path)
    g = torch.Generator().manual_seed(7)
    args = [torch.randn(R, generator=g), torch.randn(R, generator=g)] + [torch.randn(K, generator=g) for _ in range(3)]
    xD = torch.randn(coords.dirichlet.numel(), 3, generator=g, dtype=torch.float64)
    with open(path, "rb") as f:
        raw = torch.export.load(f).module()
    z_ref, x_ref = raw(*args, xD)
    z, x = rt.load_program(path)(*(a.double().numpy() for a in args), xD.numpy())
    assert torch.equal(z, z_ref) and torch.equal(x, x_ref)
    # one weight changed in the file's bytes: the checksum catches it
    data = bytearray(path.read_bytes())
    with open(tmp_path / "runtime.pt", "rb") as f:
        program = torch.export.load(f)
    tensors = [t for t in [*program.state_dict.values(), *program.constants.values()] if torch.is_tensor(t) and t.numel() >= 8]
    at = data.find(tensors[0].detach().numpy().tobytes()[:32])
    assert at > 0
    data[at + 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ArtefactError, match=r"runtime\.pt: corrupt artefact \(its weights do not match its checksum"):
        rt.load_program(path)
    assert not path.exists() and (tmp_path / "runtime.pt.corrupt").exists()
    rt.export_runtime(ae, integ, coords, path)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(ArtefactError, match=r"runtime\.pt: corrupt artefact \(torch.export cannot read it"):
        rt.load_program(path)
    # a write that fails midway (a full disk) leaves neither the file nor its temporary
    def full(*a, **k):
        (tmp_path / "runtime.tmp.pt2").write_bytes(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch.export, "save", full)
    with pytest.raises(OSError, match="No space left"):
        rt.export_runtime(ae, integ, coords, path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runtime.pt.corrupt"]


@pytest.mark.parametrize(("mode", "layout"), LAYOUTS)
def test_numpy_step_does_not_allocate(mode, layout, monkeypatch):
    """No per-step allocation: the traced peak over 20 steps stays far below
    the size of one decoded frame (n = 2000 vertices, 48 kB)."""
    _force_layout(monkeypatch, layout)
    if mode == "roots":  # 50 rods of 40 vertices
        roots = list(range(0, 2000, 40))
        coords = RelativeCoordinates(2000, roots, "roots", root_of=[v - v % 40 for v in range(2000)])
    else:
        coords = RelativeCoordinates(2000, [0, 1, 2], mode)
    torch.manual_seed(0)
    ae = Autoencoder(coords.dim, R, [32, 32], pca_dim=32)
    with torch.no_grad():  # a live branch (a zero one folds away: decoder_linear)
        ae.dec_branch.out.weight.normal_(0.0, 0.1)
    ae.eval()
    integ = LatentIntegrator(R, K, [32, 32]).eval()
    st = rt.NumpyStepper(rt.fold_networks(ae, integ, coords), np.float32)
    assert st.layout == layout and len(st.dec_W) == 2
    args = [a.numpy() for a in _inputs(coords)]
    st.step(*args)  # first call
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    for _ in range(20):
        st.step(*args)
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    assert peak < 4096, peak


@pytest.mark.parametrize("mode", ["roots", "mean", "hard_mean"])
def test_a_branch_that_outputs_zero_folds_to_the_pca_layer(mode):
    """An autoencoder that kept its PCA start (branch output layer exactly zero) folds to the PCA layer's first r
    columns alone: the same frames and Jvp as the module, without the hidden layers; a branch with one nonzero
    output weight keeps them."""
    coords = _coords(mode)
    torch.manual_seed(3)
    ae = Autoencoder(coords.dim, R, [16, 16, 8], pca_dim=12)
    ae.init_pca(torch.randn(64, coords.dim) * torch.linspace(0.2, 2.0, coords.dim))
    with torch.no_grad():  # hidden layers that would matter if the output layer were not zero
        for blk in ae.dec_branch.blocks:
            blk[0].weight.normal_(0.0, 1.0)
            blk[1].running_mean.normal_(0.0, 0.1)
    ae.eval()
    integ = LatentIntegrator(R, K, [8]).eval()
    folded = rt.fold_networks(ae, integ, coords)
    assert folded["header"]["decoder_linear"] and folded["header"]["decoder_skips"] == [] and "dec_W0" not in folded
    assert folded["dec_Wout"].shape == (coords.dim, R)
    args = _inputs(coords, seed=5, dtype=torch.float64)
    z_ref, x_ref = _reference(copy.deepcopy(ae).double(), copy.deepcopy(integ).double(), coords, args)
    st = rt.NumpyStepper(folded, np.float64)
    z, x = st.step(*(a.numpy() for a in args))
    zt, xt = rt.ExportedStepper(folded, torch.float64).step(*args)
    for a, b in ((z, z_ref), (x, x_ref), (zt.numpy(), z_ref), (xt.numpy(), x_ref)):
        assert np.allclose(a, b, rtol=0, atol=1e-12)
    vertex = int(coords.free[-1])
    row = int(np.flatnonzero(coords.encoded_vertices.numpy() == vertex)[0])
    v = torch.linspace(-1.0, 1.0, R, dtype=torch.float64)
    du_ref = rt.jvp_vertex_torch(copy.deepcopy(ae).double(), torch.as_tensor(z_ref), v, row)[1]
    assert np.allclose(st.jvp_vertex(z_ref, v.numpy(), vertex)[1], du_ref.detach().numpy(), rtol=0, atol=1e-12)
    with torch.no_grad():
        ae.dec_branch.out.weight[0, 0] = 1e-3
    live = rt.fold_networks(ae, integ, coords)
    assert not live["header"]["decoder_linear"] and len(live["header"]["decoder_skips"]) == 3


@pytest.mark.parametrize("mode", ["roots", "mean", "hard_mean"])
def test_forward_mode_jvp_equals_torch_func_jvp(mode):
    ae, integ, coords = _trained_modules(mode, seed=7)
    ae64 = copy.deepcopy(ae).double()
    st = rt.NumpyStepper(rt.fold_networks(ae, integ, coords), np.float64)
    g = torch.Generator().manual_seed(8)
    z, v = torch.randn(R, generator=g, dtype=torch.float64), torch.randn(R, generator=g, dtype=torch.float64)
    xD = torch.randn(coords.dirichlet.numel(), 3, generator=g, dtype=torch.float64)
    enc = coords.encoded_vertices.tolist()
    for vertex in (3, 7, coords.n - 1):
        row = enc.index(vertex)
        u_ref, du_ref = rt.jvp_vertex_torch(ae64, z, v, row)
        u, du = st.jvp_vertex(z.numpy(), v.numpy(), vertex)
        assert np.allclose(u, u_ref.detach().numpy(), rtol=0, atol=1e-12)
        assert np.allclose(du, du_ref.detach().numpy(), rtol=0, atol=1e-12)
        assert np.abs(du).max() > 1e-3  # a genuine, non-zero derivative
        # with the Dirichlet origin: the decoded vertex of the full decode
        x_v, _ = st.jvp_vertex(z.numpy(), v.numpy(), vertex, xD.numpy())
        x_full = decode_latents(ae64, coords, z[None], xD[None])[0, vertex]
        assert np.allclose(x_v, x_full.detach().numpy(), rtol=0, atol=1e-12)
    if mode == "roots":  # a prescribed root does not depend on the latent
        x_v, dx = st.jvp_vertex(z.numpy(), v.numpy(), 6, xD.numpy())
        assert np.array_equal(dx, np.zeros(3)) and np.array_equal(x_v, xD[1].numpy())
    # the full decoder Jacobian by forward mode against torch.func.jacfwd
    x, J = st.decode_jacobian(z.numpy(), xD.numpy())
    J_ref = torch.func.jacfwd(lambda q: decode_latents(ae64, coords, q[None], xD[None])[0].reshape(-1))(z)
    assert np.allclose(J, J_ref.detach().numpy(), rtol=0, atol=1e-12)
    assert np.allclose(x, decode_latents(ae64, coords, z[None], xD[None])[0].detach().numpy(), atol=1e-12)


def test_every_stepper_is_timed_alike():
    """The NumPy, compiled, exported and eager steppers take the same NumPy frame (each converts it with its own
    ``inputs``): time_step reports each part, and their steps agree."""
    ae, integ, coords = _trained_modules("mean", seed=9)
    folded = rt.fold_networks(ae, integ, coords)
    steppers = {"numpy": rt.NumpyStepper(folded), "exported": rt.ExportedStepper(folded), "eager": EagerStepper(ae, integ, coords)}
    if rc.available():
        steppers["compiled"] = rc.CompiledStepper(folded)
    frame = [a.numpy() for a in _inputs(coords)]
    x_ref = steppers["numpy"].step(*frame)[1].copy()
    for name, st in steppers.items():
        assert isinstance(st, rt.Stepper), name  # the protocol's attributes and methods
        t = rt.time_step(st, *frame, repeats=5, warmup=1)
        assert set(t) == {"integrate_ms", "decode_ms", "step_ms"}, name
        assert all(v > 0 and np.isfinite(v) for v in t.values()), name
        x = np.asarray(st.step(*st.inputs(*frame))[1])
        assert x.dtype == np.float64 and np.abs(x - x_ref).max() < 1e-5 * np.abs(x_ref).max(), name


# ---------------------------------------------------------------------------
# the compiled runtime (latentsim.runtime.compiled): one numba kernel call per step
# ---------------------------------------------------------------------------
needs_numba = pytest.mark.skipif(not rc.available(), reason="numba is not installed")


def _big_coords(mode: str, rod: int = 40) -> RelativeCoordinates:
    """2,000 vertices: many output segments; rods of ``rod`` vertices (longer than a segment when rod > 128),
    or scattered Dirichlet vertices (several copy-back runs)."""
    if mode == "roots":
        roots = list(range(0, 2000, rod))
        return RelativeCoordinates(2000, roots, "roots", root_of=[v - v % rod for v in range(2000)])
    return RelativeCoordinates(2000, [0, 1, 2, 10, 11, 500, 1999], mode)


def _decoder(coords, kind: str) -> Autoencoder:
    """An eval-mode autoencoder whose folded decoder takes each of the runtime's paths."""
    torch.manual_seed(4)
    widths, pca = {"hidden": ([32, 32, 16], 48), "mid": ([32, 32], 8), "linear": ([16], 24), "no_hidden": ([], 24)}[kind]
    ae = Autoencoder(coords.dim, R, widths, pca_dim=pca)
    ae.init_pca(torch.randn(64, coords.dim) * torch.linspace(0.2, 2.0, coords.dim) + 0.1)
    with torch.no_grad():
        if kind != "linear":  # a live branch, with BatchNorm statistics that matter
            ae.dec_branch.out.weight.normal_(0.0, 0.2)
            ae.dec_branch.out.bias.normal_(0.0, 0.1)
        for blk in ae.dec_branch.blocks:
            blk[1].running_mean.normal_(0.0, 0.1)
            blk[1].running_var.uniform_(0.5, 2.0)
    return ae.eval()


@needs_numba
@pytest.mark.parametrize(("mode", "layout"), LAYOUTS)
def test_compiled_runtime_matches_the_modules(mode, layout, monkeypatch):
    """float64: the compiled step, integrate and decode equal the PyTorch modules to round-off in every coordinate
    mode and output layout; the prescribed vertices are re-applied exactly; float32 agrees with the NumPy runtime."""
    _force_layout(monkeypatch, layout)
    ae, integ, coords = _trained_modules(mode)
    folded = rt.fold_networks(ae, integ, coords)
    args = _inputs(coords, dtype=torch.float64)
    z_ref, x_ref = _reference(copy.deepcopy(ae).double(), copy.deepcopy(integ).double(), coords, args)
    cs = rc.CompiledStepper(folded, np.float64)
    assert cs.layout == layout
    a = [t.numpy() for t in args]
    z, x = cs.step(*a)
    assert np.allclose(z, z_ref, rtol=0, atol=1e-12) and np.allclose(x, x_ref, rtol=0, atol=1e-12)
    zi = cs.integrate(*a[:5]).copy()
    assert np.allclose(zi, z_ref, rtol=0, atol=1e-12)
    assert np.allclose(cs.decode(zi, a[-1]), x_ref, rtol=0, atol=1e-12)
    if mode != "mean":
        assert np.array_equal(x[coords.dirichlet.numpy()], a[-1])
    a32 = [t.numpy() for t in _inputs(coords)]
    z32, x32 = rc.CompiledStepper(folded, np.float32).step(*a32)
    zn, xn = rt.NumpyStepper(folded, np.float32).step(*a32)
    assert z32.dtype == np.float32 and x32.dtype == np.float64
    assert np.abs(z32 - zn).max() < 1e-5 and np.abs(x32 - xn).max() < 1e-5 * np.abs(xn).max()


@needs_numba
@pytest.mark.parametrize("kind", ["hidden", "mid", "linear", "no_hidden"])
@pytest.mark.parametrize(("mode", "rod", "layout"), [("roots", 40, None), ("roots", 250, None), ("mean", 0, None), ("hard_mean", 0, "full"), ("hard_mean", 0, "scatter")])
def test_compiled_runtime_on_large_meshes(kind, mode, rod, layout, monkeypatch):
    """2,000 vertices (the output in many segments, rods longer than a segment, Dirichlet vertices in several
    runs), each folded decoder shape: the compiled decode equals the NumPy runtime's.  hard_mean scattered
    sums the Dirichlet mean while it copies the prescribed vertices back (before the free ones are written)."""
    if layout:
        _force_layout(monkeypatch, layout)
    coords = _big_coords(mode, rod or 40)
    ae = _decoder(coords, kind)
    integ = LatentIntegrator(R, K, [16]).eval()
    folded = rt.fold_networks(ae, integ, coords)
    assert folded["header"]["decoder_linear"] == (kind == "linear")
    assert folded["header"]["decoder_mid"] == (kind == "mid")
    cs, ns = rc.CompiledStepper(folded, np.float64), rt.NumpyStepper(folded, np.float64)
    free = 2000 - 7 if layout == "scatter" else 2000
    assert cs.chunks == -(-3 * free // 384) and cs.segments >= cs.chunks and (mode != "hard_mean" or cs.dirichlet_runs == 4)  # [0, 1, 2], [10, 11], [500], [1999]
    assert cs.layout == (layout or "full") and cs.fused_mean == (layout == "scatter")
    a = [t.numpy() for t in _inputs(coords, seed=8, dtype=torch.float64)]
    z, x = cs.step(*a)
    zn, xn = ns.step(*a)
    assert np.allclose(z, zn, rtol=0, atol=1e-12)
    assert np.allclose(x, xn, rtol=0, atol=1e-11)
    assert np.abs(xn).max() > 0.1


@needs_numba
@pytest.mark.parametrize("kind", ["hidden", "mid", "linear", "no_hidden"])
def test_the_step_floor_is_one_pass_of_the_models_own_output_layer(kind):
    """output_pass evaluates the runtime's last layer, at its own input width, over every value it writes, and
    nothing else: b + sum_i h_i W_i with h = 0.5, against the NumPy runtime's output layer; the timing helper
    records it beside the step."""
    from latentsim.latent.timing import time_steppers

    coords = _big_coords("mean")
    ae = _decoder(coords, kind)
    folded = rt.fold_networks(ae, LatentIntegrator(R, K, [16]).eval(), coords)
    cs, ns = rc.CompiledStepper(folded, np.float32), rt.NumpyStepper(folded, np.float32)
    call, y = cs.output_pass()
    call()
    A = ns.output.A.astype(np.float64)
    assert y.shape == (A.shape[1],) == (3 * 2000,) and A.shape[0] > 1
    assert np.allclose(y, A[-1] + 0.5 * A[:-1].sum(0), rtol=1e-5, atol=1e-6 * np.abs(A).max())
    a = [t.numpy() for t in _inputs(coords, seed=3)]
    timing = time_steppers({"numpy": ns, "compiled": cs}, a[0], a[1], a[2], a[5], repeats=5)
    assert timing["floor_ms"] > 0 and np.isfinite(timing["step_ms"])


@needs_numba
@pytest.mark.parametrize("mode", ["roots", "hard_mean"])
def test_compiled_rollout_writes_each_frame_and_keeps_nan(mode, tmp_path):
    """A rollout through the exported file writes every frame into its own row (z_out/x_out) and equals the NumPy
    runtime's; a NaN weight gives NaN latents and positions (fastmath keeps NaNs: a diverging rollout must stop)."""
    ae, integ, coords = _trained_modules(mode, seed=5)
    rt.export_runtime(ae, integ, coords, tmp_path / "runtime.npz")
    cs, ns = rc.load_runtime(tmp_path / "runtime.npz"), rt.load_runtime(tmp_path / "runtime.npz")
    g = torch.Generator().manual_seed(6)
    T = 15
    bc = torch.randn(T, K, generator=g).numpy()
    xD = torch.randn(T, coords.dirichlet.numel(), 3, generator=g, dtype=torch.float64).numpy()
    z0, z1 = (torch.randn(R, generator=g).numpy() for _ in range(2))
    out_c, out_n = rt.rollout_runtime(cs, z0, z1, bc, xD), rt.rollout_runtime(ns, z0, z1, bc, xD)
    assert np.isfinite(out_c["positions"]).all()
    assert np.abs(out_c["latents"] - out_n["latents"]).max() < 1e-5
    assert np.abs(out_c["positions"] - out_n["positions"]).max() < 1e-5 * np.abs(out_n["positions"]).max()
    assert not np.allclose(out_c["positions"][5], out_c["positions"][6])  # distinct frames, not one buffer
    folded = rt.fold_networks(ae, integ, coords)
    folded["int_W0"][0, 0] = np.nan
    z, x = rc.CompiledStepper(folded).step(*[t.numpy() for t in _inputs(coords)])
    assert np.isnan(z).all() and np.isnan(x[coords.free.numpy()]).all()


@needs_numba
def test_compiled_runtime_refuses_what_it_cannot_do():
    ae, integ, coords = _trained_modules("mean", seed=2)
    dec_only = rc.CompiledStepper(rt.fold_decoder(ae, coords))
    a = [t.numpy() for t in _inputs(coords)]
    with pytest.raises(ValueError, match="decoder only"):
        dec_only.step(*a)
    assert dec_only.decode(a[0], a[-1]).shape == (coords.n, 3)
    cs = rc.CompiledStepper(rt.fold_networks(ae, integ, coords))
    with pytest.raises(ValueError, match="C-contiguous float64"):
        cs.step(*a, x_out=np.empty((coords.n, 6))[:, :3])
    with pytest.raises(ValueError, match="C-contiguous float64"):
        cs.decode(a[0], a[-1], out=np.empty((coords.n, 3), np.float32))


@needs_numba
def test_float32_silu_without_libm_is_float32_accurate():
    """The float32 kernel's SiLU (exp as a Taylor polynomial squared 8 times) is within float32's epsilon of the
    float64 closed form over [-80, 80], exact beyond (t for t > 80, ~0 below -80), and keeps NaN."""
    t = np.concatenate([np.linspace(-80.0, 80.0, 200_001), [-1e4, -100.0, 100.0, 1e4, np.nan]]).astype(np.float32)
    y = t.copy()
    rc._silu32(y, len(y))
    t64 = t.astype(np.float64)
    with np.errstate(over="ignore"):
        ref = t64 / (1.0 + np.exp(-t64))
    inside = np.abs(t64) <= 80
    rel = np.abs(y[inside] - ref[inside]) / np.maximum(np.abs(ref[inside]), np.finfo(np.float32).tiny)
    assert rel.max() < np.finfo(np.float32).eps
    assert y[-3] == 100.0 and y[-2] == 1e4 and abs(y[-4]) < 1e-30 and abs(y[-5]) < 1e-30 and np.isnan(y[-1])


# ---------------------------------------------------------------------------
# the encoder, and a trained model stepped from full-space frames (runtime.load)
# ---------------------------------------------------------------------------
def _frames(coords, T: int, seed: int):
    """T frames of positions (T, n, 3), Dirichlet positions (T, m, 3) that are those of the frames, and parameters (T, K)."""
    g = torch.Generator().manual_seed(seed)
    x = 0.3 + torch.randn(T, coords.n, 3, generator=g, dtype=torch.float64)
    xD = x[:, coords.dirichlet].clone()
    return x, xD, torch.randn(T, K, generator=g)


@pytest.mark.parametrize("widths", [[16, 16, 8], [12], []])
@pytest.mark.parametrize("mode", ["roots", "mean", "hard_mean"])
def test_encoder_matches_encode_positions(mode, widths):
    """The folded encoder gives the pipeline's latents (encode_positions: float64 relative coordinates, float32
    network) to float32 rounding, and the float64 module's to 1e-12 in float64; with and without identity
    skips and hidden layers; a whole sequence in one call."""
    ae, integ, coords = _trained_modules(mode, seed=11)
    if widths != [16, 16, 8]:  # another shape of encoder, BatchNorm statistics and output layer made non-trivial
        torch.manual_seed(12)
        ae = Autoencoder(coords.dim, R, widths, pca_dim=12)
        with torch.no_grad():
            ae.enc_branch.out.weight.normal_(0.0, 0.3)
            for blk in ae.enc_branch.blocks:
                blk[1].running_mean.normal_(0.0, 0.2)
                blk[1].running_var.uniform_(0.5, 2.0)
        ae.eval()
    x, xD, _ = _frames(coords, 5, seed=13)
    folded = rt.fold_networks(ae, integ, coords)
    assert folded["header"]["encoder"] and folded["header"]["version"] == rt.VERSION == 2
    z_ref = encode_positions(ae, coords, x, xD).numpy()
    assert np.abs(z_ref).max() > 0.1
    z = rt.NumpyStepper(folded, np.float32).encode(x.numpy(), xD.numpy())
    assert z.dtype == np.float32 and z.shape == (5, R)
    assert np.abs(z - z_ref).max() < 1e-5 * np.abs(z_ref).max()
    ae64 = copy.deepcopy(ae).double()
    with torch.no_grad():
        z64_ref = ae64.encode(coords.encode(x, xD)).numpy()
    z64 = rt.NumpyStepper(folded, np.float64).encode(x[2].numpy(), xD[2].numpy())
    assert np.allclose(z64, z64_ref[2], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match=r"positions: need shape \(\.\.\., 12, 3\)"):
        rt.NumpyStepper(folded).encode(x[0, :5].numpy(), xD[0].numpy())


@pytest.mark.parametrize("mode", ["roots", "mean", "hard_mean"])
def test_loaded_model_encodes_and_steps_as_the_pipeline_rolls_out(mode, tmp_path):
    """runtime.load(folder): encode two full-space frames, step with the parameters and Dirichlet positions of each
    frame: the rollout stage's frames (encode_positions, then latent.rollout in PyTorch) to float32 rounding."""
    ae, integ, coords = _trained_modules(mode, seed=5)
    T = 12
    x, xD, bc = _frames(coords, T, seed=14)
    z01 = encode_positions(ae, coords, x[:2], xD[:2])
    ref = rollout(integ, ae, coords, z01[0], z01[1], bc, xD)
    assert ref["diverged_frame"] == -1
    rt.export_runtime(ae, integ, coords, tmp_path / "runtime.npz")
    model = rt.load(tmp_path)
    assert (model.r, model.k, model.n, model.m) == (R, K, coords.n, coords.dirichlet.numel())
    z = model.encode(x[0].numpy(), x[1].numpy(), xD[:2].numpy(), bc[:2].numpy())
    assert np.abs(z - z01.numpy()).max() < 1e-5 * np.abs(z01.numpy()).max()
    X = np.stack([model.step(bc[t].numpy(), xD[t].numpy()) for t in range(2, T)])
    scale = float(ref["positions"].abs().max())
    assert np.abs(X - ref["positions"][2:].numpy()).max() < 1e-4 * scale
    assert np.abs(np.diff(X, axis=0)).max() > 1e-2 * scale  # the frames move
    assert np.abs(model.latent - ref["latents"][-1].numpy()).max() < 1e-4
    # start from stored latents instead: the same frames; xD omitted keeps the last frame's (a boundary at rest)
    again = rt.load(tmp_path / "runtime.npz")
    again.start(z[0], z[1], bc[:2].numpy(), xD[1].numpy())
    assert np.array_equal(again.step(bc[2].numpy(), xD[2].numpy()), X[0])
    assert np.array_equal(again.step(bc[3].numpy()), model.stepper.decode(again.latent, xD[2].numpy()))
    with pytest.raises(ValueError, match=r"p need shape \(6,\)"):
        again.step(bc[:2].numpy())
    with pytest.raises(RuntimeError, match="encode two frames"):
        rt.load(tmp_path).step(bc[2].numpy())


def test_a_model_trained_with_the_origin_appends_it_from_the_dirichlet_positions(tmp_path):
    """An integrator trained with ``integrator.origin_input`` takes the frame's mean Dirichlet position after p:
    the loaded model appends it from the xD it is given (the user passes the K parameters alone) and steps as
    the pipeline's rollout does."""
    ae, _, coords = _trained_modules("mean", seed=5)
    g = torch.Generator().manual_seed(6)
    integ = LatentIntegrator(R, K + 3, [20, 24], origin=True)
    Z, P = torch.randn(96, 3, R, generator=g), torch.randn(96, 3, K + 3, generator=g) + 1.0
    integ.fit_normalization(Z[:, 0], Z[:, 1], Z[:, 2], P[:, 0], P[:, 1], P[:, 2])
    with torch.no_grad():
        integ.mlp[0].weight[:, -3:] *= 50.0  # the origin matters to the step
    integ.eval()
    T = 8
    x, xD, bc = _frames(coords, T, seed=14)
    z01 = encode_positions(ae, coords, x[:2], xD[:2])
    ref = rollout(integ, ae, coords, z01[0], z01[1], bc, xD)
    rt.export_runtime(ae, integ, coords, tmp_path / "runtime.npz")
    model = rt.load(tmp_path)
    assert model.origin and model.k == K
    model.encode(x[0].numpy(), x[1].numpy(), xD[:2].numpy(), bc[:2].numpy())
    X = np.stack([model.step(bc[t].numpy(), xD[t].numpy()) for t in range(2, T)])
    scale = float(ref["positions"].abs().max())
    assert np.abs(X - ref["positions"][2:].numpy()).max() < 1e-4 * scale
    # the same frames with the origin left at zero: another motion, so the model does use what it appends
    blind = rollout(lambda z1, z2, p, p1, p2: integ(z1, z2, *(torch.cat([q[:, :K], 0 * q[:, K:]], -1) for q in (p, p1, p2))),
                    ae, coords, z01[0], z01[1], torch.cat([bc, torch.zeros(T, 3)], -1), xD)  # fmt: skip
    assert np.abs(X - blind["positions"][2:].numpy()).max() > 1e-2 * scale


def test_the_frame_of_three_points_is_a_rotation_that_turns_with_them():
    """runtime.frame.orthonormal_frame: a proper rotation (F^T F = I, det 1) whose first axis points from the first
    point to the second; turning and moving the points turns it alike, F(Q p + t) = Q F(p); one frame in NumPy
    (the runtime's scalar path), a batch in NumPy and in torch agree."""
    from latentsim.runtime.frame import orthonormal_frame

    rng = np.random.default_rng(3)
    p = rng.normal(size=(6, 3, 3))
    F = orthonormal_frame(p)
    assert np.allclose(F.swapaxes(-1, -2) @ F, np.eye(3), atol=1e-14) and np.allclose(np.linalg.det(F), 1.0, atol=1e-14)
    assert np.allclose(F[..., 0], (p[:, 1] - p[:, 0]) / np.linalg.norm(p[:, 1] - p[:, 0], axis=-1, keepdims=True), atol=1e-14)
    Q = torch.linalg.matrix_exp(torch.tensor([[0.0, -0.4, 1.1], [0.4, 0.0, -0.3], [-1.1, 0.3, 0.0]], dtype=torch.float64)).numpy()
    assert np.allclose(orthonormal_frame(p @ Q.T + [1.0, -2.0, 0.5]), Q @ F, atol=1e-13)
    one = np.stack([orthonormal_frame(q) for q in p])
    assert np.allclose(one, F, atol=1e-15) and np.allclose(orthonormal_frame(torch.as_tensor(p)).numpy(), F, atol=1e-15)


@pytest.mark.parametrize("mode", ["mean", "hard_mean"])
def test_a_model_in_a_rigid_frame_steps_as_the_rollout_with_every_runtime(mode, tmp_path):
    """``autoencoder.rigid_frame``: the runtime file records the frame; the loaded model (NumPy, and compiled where
    numba imports) carries p and the positions into the frame and out again at the xD it is given, encodes and
    steps as the pipeline does; each stepper the rollout stage times decodes the rollout's frames; and the same
    latents decoded without the frame are another motion (the boundary turns)."""
    from latentsim.latent.timing import rigid_frame_steppers

    ae, _, plain = _trained_modules(mode, seed=5)
    g = torch.Generator().manual_seed(8)
    rest = 0.3 + torch.randn(plain.n, 3, generator=g, dtype=torch.float64)
    coords = RelativeCoordinates(plain.n, [0, 1, 2], mode, rigid_rest=rest[[0, 1, 2]])
    integ = LatentIntegrator(R, K + 9, [20, 24])
    Z, P = torch.randn(96, 3, R, generator=g), torch.randn(96, 3, K + 9, generator=g)
    integ.fit_normalization(Z[:, 0], Z[:, 1], Z[:, 2], P[:, 0], P[:, 1], P[:, 2])
    integ.eval()
    T = 8
    turn = torch.stack([torch.linalg.matrix_exp(0.3 * t * torch.tensor([[0.0, -1, 0.5], [1, 0, -0.2], [-0.5, 0.2, 0]], dtype=torch.float64)) for t in range(T)])
    x = (rest + 0.05 * torch.randn(T, plain.n, 3, generator=g, dtype=torch.float64)) @ turn.transpose(-1, -2) + 0.1
    xD = x[:, [0, 1, 2]].clone()
    bc = torch.randn(T, K, generator=g)
    z01 = encode_positions(ae, coords, x[:2], xD[:2])
    ref = rollout(integ, ae, coords, z01[0], z01[1], bc, xD)
    scale = float(ref["positions"].abs().max())
    rt.export_runtime(ae, integ, coords, tmp_path / "runtime.npz")
    models = [rt.load(tmp_path)] + ([rt.TrainedModel(rc.load_runtime(tmp_path / "runtime.npz"))] if rc.available() else [])
    for model in models:
        assert model.rigid and model.k == K
        z = model.encode(x[0].numpy(), x[1].numpy(), xD[:2].numpy(), bc[:2].numpy())
        assert np.abs(z - z01.numpy()).max() < 1e-4 * float(z01.abs().max())
        X = np.stack([model.step(bc[t].numpy(), xD[t].numpy()) for t in range(2, T)])
        assert np.abs(X - ref["positions"][2:].numpy()).max() < 1e-4 * scale
    folded = rt.fold_networks(ae, integ, coords)
    compiled = {"compiled": rc.CompiledStepper(folded)} if rc.available() else {}  # carries out in its own kernel
    steppers = rigid_frame_steppers({"numpy": rt.NumpyStepper(folded), "exported": rt.ExportedStepper(folded), "eager": EagerStepper(ae, integ, coords),
                                     **compiled}, coords)  # fmt: skip
    assert isinstance(steppers["numpy"], rt.RigidFrameStepper) and not isinstance(steppers["eager"], rt.RigidFrameStepper)
    for name, st in steppers.items():
        z4, p4 = ref["latents"][4].numpy(), np.zeros(K + 9, dtype=np.float32)
        x5 = np.asarray(st.decode(*st.inputs(z4, z4, p4, p4, p4, xD[4].numpy())[::5]))
        assert np.abs(x5 - ref["positions"][4].numpy()).max() < 1e-4 * scale, name
        if name != "eager":  # into a caller's buffer, as the timings step
            buf = np.empty((plain.n, 3))
            z4c, xD4 = st.inputs(z4, z4, p4, p4, p4, xD[4].numpy())[::5]
            assert st.decode(z4c, xD4, out=buf) is buf and np.abs(buf - ref["positions"][4].numpy()).max() < 1e-4 * scale, name
    with torch.no_grad():
        unturned = decode_latents(ae, plain, ref["latents"], xD)
    assert np.abs(unturned.numpy() - ref["positions"].numpy()).max() > 1e-2 * scale


def test_a_runtime_file_without_encoder_steps_but_says_how_to_encode(tmp_path):
    """A format version 1 file (before the encoder was exported) still loads and steps from stored latents;
    encode() names the file and says to rerun the rollout job."""
    ae, integ, coords = _trained_modules("roots", seed=5)
    folded = rt.fold_networks(ae, integ, coords)
    header = {k: v for k, v in folded["header"].items() if not k.startswith("encoder")} | {"version": 1}
    arrays = {k: v for k, v in folded.items() if k != "header" and not k.startswith("enc_")}
    old = tmp_path / "runtime.npz"
    np.savez(old, header=np.asarray(json.dumps(header)), **arrays)
    model = rt.load(old)
    x, xD, bc = _frames(coords, 3, seed=15)
    z01 = encode_positions(ae, coords, x[:2], xD[:2]).numpy()
    model.start(z01[0], z01[1], bc[:2].numpy(), xD[1].numpy())
    assert np.isfinite(model.step(bc[2].numpy(), xD[2].numpy())).all()
    with pytest.raises(ValueError, match=rf"{re.escape(str(old))}: .*format version 1.*rerun the rollout job"):
        model.encode(x[0].numpy(), x[1].numpy(), xD[0].numpy(), bc[:2].numpy())
    with pytest.raises(FileNotFoundError, match="runtime.npz"):
        rt.load(tmp_path / "elsewhere")


def _load_example():
    spec = importlib.util.spec_from_file_location("step_trained_model", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_example_steps_a_trained_model_as_the_pipeline_rolls_out(tmp_path, capsys):
    """examples/step_trained_model.py on a rollout folder of a tiny trained model and a trajectories file: its NumPy
    frames and its torch.export program's are the rollout stage's (encode_positions, then latent.rollout)."""
    ae, integ, coords = _trained_modules("roots", seed=5)
    T = 10
    x, xD, bc = _frames(coords, T, seed=16)
    folder = tmp_path / "rollout"
    rt.export_runtime(ae, integ, coords, folder / "runtime.npz")
    rt.export_runtime(ae, integ, coords, folder / "runtime.pt")
    with h5py.File(tmp_path / "trajectories.h5", "w") as f:
        f["rest_positions"] = x[0].numpy()
        for name, split in (("train_a", "train"), ("test_a", "test")):
            g = f.create_group(f"sequences/{name}")
            g.attrs["split"] = split
            g["positions"], g["dirichlet_positions"], g["bc"] = x.numpy(), xD.numpy(), bc.numpy()
    z01 = encode_positions(ae, coords, x[:2], xD[:2])
    ref = rollout(integ, ae, coords, z01[0], z01[1], bc, xD)["positions"].numpy()
    out = _load_example().main([str(folder), "--trajectories", str(tmp_path / "trajectories.h5")])
    printed = capsys.readouterr().out
    assert out["sequence"] == "test_a" and "test_a: frames 0, 1 encoded, 8 stepped" in printed and "torch.export program" in printed
    scale = np.abs(ref).max()
    assert np.abs(out["positions"][2:] - ref[2:]).max() < 1e-4 * scale
    assert np.abs(out["torch_export_positions"][2:] - ref[2:]).max() < 1e-4 * scale
    assert np.abs(out["positions"][2:] - x[2:].numpy()).max() > 1e-2 * scale  # stepped, not copied from the file
    assert out["numpy_ms"] > 0 and out["mean_error"] > 0
    short = _load_example().main([str(folder / "runtime.npz"), "--trajectories", str(tmp_path / "trajectories.h5"), "--frames", "4", "--no-torch-export"])
    assert short["positions"].shape == (4, coords.n, 3) and "torch_export_positions" not in short
    assert np.array_equal(short["positions"], out["positions"][:4])
