r"""St. Venant-Kirchhoff elasticity on linear tetrahedra.

Kinematics (Sifakis & Barbic 2012, "FEM simulation of 3D deformable solids",
SIGGRAPH course notes, sections 3-4).  A tet with rest vertices X_0..X_3 and
deformed vertices x_0..x_3 has the constant deformation gradient

    F = Ds Dm^{-1},   Ds = [x1-x0, x2-x0, x3-x0],   Dm = [X1-X0, X2-X0, X3-X0],

rest volume W = det(Dm)/6 > 0, and elastic energy W * Psi(F) with the StVK
energy density

    E   = (F^T F - I) / 2                          (Green strain)
    Psi = mu ||E||_F^2 + lam/2 tr(E)^2
    P   = dPsi/dF = F S,   S = 2 mu E + lam tr(E) I  (first / second Piola).

F is linear in the 12 stencil coordinates: F_ij = sum_a x_{a,i} D_{a,j} with
D (4, 3) the gradients of the barycentric coordinates (rows of Dm^{-1} and
minus their sum), so vec(F) = B x_e with B (9, 12) and

    g_e = W B^T vec(P)  (= W D P^T as a (4, 3) array),
    H_e = W B^T (dP/dF) B,
    dP  = dF S + F dS,  dS = 2 mu dE + lam tr(dE) I,  dE = (dF^T F + F^T dF)/2.

PSD projection for Newton (Teran et al. 2005, "Robust quasistatic finite
elements and flesh simulation"; Smith et al. 2019, "Analytic eigensystems for
isotropic distortion energies").  With the rotation-variant SVD
F = U diag(sigma) V^T (det U = det V = +1, the smallest sigma carries the sign
of det F) the 9x9 Hessian dP/dF has the closed-form eigensystem

    scaling (3): eigenpairs (alpha_k, w_k) of the 3x3 matrix
                 A_ii = mu (3 sigma_i^2 - 1) + lam T + lam sigma_i^2,
                 A_ij = lam sigma_i sigma_j,     T = sum_j (sigma_j^2 - 1)/2,
                 eigenmatrix U diag(w_k) V^T;
    flip  (ij):  mu (sigma_i^2 + sigma_j^2 - 1) + lam T + mu sigma_i sigma_j,
                 eigenmatrix U (e_i e_j^T + e_j e_i^T) V^T / sqrt 2;
    twist (ij):  mu (sigma_i^2 + sigma_j^2 - 1) + lam T - mu sigma_i sigma_j,
                 eigenmatrix U (e_i e_j^T - e_j e_i^T) V^T / sqrt 2.

(These are the Hessian of Psi(diag sigma), which is block diagonal by the
reflection symmetries of Psi; the flip/twist values equal Teran's
(psi_i -/+ psi_j)/(sigma_i -/+ sigma_j) with the division carried out, so they
stay exact at repeated singular values.)  Clamping the eigenvalues at zero
gives the projected element Hessian

    H_e^+ = W sum_k max(lambda_k, 0) g_k g_k^T,   g_k = B^T vec(Q_k).

Note that this projects dP/dF in F-space, which differs from the eigenvalue
clamp of the 12x12 element Hessian unless D^T D is a multiple of the identity
(e.g. for regular tets); both are PSD and both are exact where dP/dF is PSD.

The closed forms run in NumPy (float64), with a vectorised cyclic-Jacobi 3x3
eigensolver, because LAPACK's batched SVD of 3x3 matrices is dominated by
per-matrix overhead; they return torch tensors.  ``local_energy`` is pure torch
and autograd-differentiable.
"""

from __future__ import annotations

import numpy as np
import torch

from latentsim.physics.base import EnergyTerm, subset_weights

_TINY = np.finfo(np.float64).tiny
_PAIRS = ((0, 1), (0, 2), (1, 2))


# --------------------------------------------------------------------------
# material parameters and rest geometry
# --------------------------------------------------------------------------
def lame(youngs_modulus, poisson_ratio):
    """Lame parameters from Young's modulus Y and Poisson's ratio nu.

    mu = Y / (2 (1 + nu)),  lam = Y nu / ((1 + nu)(1 - 2 nu)).

    Parameters
    ----------
    youngs_modulus, poisson_ratio : float or tensor (broadcastable), with
        -1 < nu < 1/2.

    Returns
    -------
    (mu, lam) : same type/shape as the broadcast inputs.
    """
    nu = torch.as_tensor(poisson_ratio, dtype=torch.float64)
    if bool(torch.any((nu <= -1.0) | (nu >= 0.5))):
        raise ValueError(f"Poisson ratio must lie in (-1, 0.5), got {poisson_ratio}")
    mu = youngs_modulus / (2.0 * (1.0 + poisson_ratio))
    lam = youngs_modulus * poisson_ratio / ((1.0 + poisson_ratio) * (1.0 - 2.0 * poisson_ratio))
    return mu, lam


def _edge_matrix(positions: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """Dm (E, 3, 3) with columns X1-X0, X2-X0, X3-X0."""
    X = positions[tets]  # (E, 4, 3)
    return (X[:, 1:, :] - X[:, :1, :]).transpose(1, 2)


def tet_volumes(positions: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """Signed tet volumes det([x1-x0, x2-x0, x3-x0]) / 6.

    positions : (n, 3); tets : (E, 4) long.  Returns (E,).
    """
    return torch.linalg.det(_edge_matrix(positions, tets)) / 6.0


def lumped_masses(rest_positions: torch.Tensor, tets: torch.Tensor, density) -> torch.Tensor:
    """Lumped vertex masses: each vertex gets density * |W_e| / 4 from each incident tet.

    Parameters
    ----------
    rest_positions : (n, 3); tets : (E, 4) long;
    density : float or (E,) tensor [kg/m^3].

    Returns
    -------
    (n,) tensor of masses; they sum to sum_e density_e |W_e|.
    """
    tets = torch.as_tensor(tets, dtype=torch.long)
    vol = tet_volumes(rest_positions, tets).abs()
    m_e = torch.as_tensor(density, dtype=vol.dtype) * vol / 4.0
    m_e = m_e.expand(vol.shape[0])
    masses = torch.zeros(rest_positions.shape[0], dtype=vol.dtype, device=vol.device)
    return masses.index_add_(0, tets.reshape(-1), m_e.repeat_interleave(4))


def stvk_density(F: torch.Tensor, mu, lam) -> torch.Tensor:
    """StVK energy density Psi(F) = mu ||E||_F^2 + lam/2 tr(E)^2, E = (F^T F - I)/2.

    F : (..., 3, 3); mu, lam broadcastable to (...).  Returns (...).
    """
    C = F.transpose(-1, -2) @ F
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    Eg = 0.5 * (C - eye)
    trE = Eg.diagonal(dim1=-2, dim2=-1).sum(-1)
    return mu * (Eg * Eg).sum((-1, -2)) + 0.5 * lam * trE * trE


# --------------------------------------------------------------------------
# batched 3x3 linear algebra in NumPy, "structure of arrays" layout: a batch
# of 3x3 matrices is an array (3, 3, N), so every operation is an elementwise
# NumPy op on contiguous length-N rows (LAPACK's batched 3x3 SVD/eigh spend
# most of their time in per-matrix overhead).
# --------------------------------------------------------------------------
def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products of (3, N) vector batches."""
    return np.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _jacobi_eigh3(A: np.ndarray, max_sweeps: int = 12, tol: float = 1e-31):
    """Eigen-decomposition of symmetric 3x3 matrices by cyclic Jacobi rotations.

    Parameters
    ----------
    A : (3, 3, N) float64, symmetric in its first two axes.

    Returns
    -------
    w : (3, N) eigenvalues (unsorted); V : (3, 3, N) orthogonal, columns
    V[:, k] the eigenvectors, A = V diag(w) V^T.  Matrices whose off-diagonal
    norm^2 <= tol * ||A||_F^2 are converged; after two sweeps only the
    unconverged ones are iterated (quadratic convergence, 3-4 sweeps).
    """
    n = A.shape[-1]
    d = [A[0, 0].copy(), A[1, 1].copy(), A[2, 2].copy()]
    o = {(0, 1): 0.5 * (A[0, 1] + A[1, 0]), (0, 2): 0.5 * (A[0, 2] + A[2, 0]),
         (1, 2): 0.5 * (A[1, 2] + A[2, 1])}
    V = [[np.full(n, float(i == j)) for j in range(3)] for i in range(3)]
    w_out, V_out = np.empty((3, n)), np.empty((3, 3, n))
    idx = slice(None)  # indices of the matrices still iterated

    def write_back():
        w_out[:, idx] = d
        V_out[:, :, idx] = V

    for sweep in range(max_sweeps):
        off = o[0, 1] ** 2 + o[0, 2] ** 2 + o[1, 2] ** 2
        active = off > tol * (d[0] ** 2 + d[1] ** 2 + d[2] ** 2 + 2.0 * off)
        n_active = int(np.count_nonzero(active))
        if n_active == 0:
            break
        if sweep >= 2 and n_active < 0.5 * active.shape[0]:
            write_back()
            sel = np.flatnonzero(active)
            idx = sel if isinstance(idx, slice) else idx[sel]
            d = [v[sel] for v in d]
            o = {key: v[sel] for key, v in o.items()}
            V = [[v[sel] for v in row] for row in V]
        for p, q in _PAIRS:
            r = 3 - p - q
            apq = o[p, q]
            # t = tan(phi) of the rotation annihilating A_pq (smaller root)
            tau = 0.5 * (d[q] - d[p])
            t = apq * np.copysign(1.0, tau) / (np.abs(tau) + np.sqrt(tau * tau + apq * apq) + _TINY)
            c = 1.0 / np.sqrt(t * t + 1.0)
            s = t * c
            d[p] = d[p] - t * apq
            d[q] = d[q] + t * apq
            o[p, q] = np.zeros_like(apq)
            rp, rq = (min(r, p), max(r, p)), (min(r, q), max(r, q))
            arp, arq = o[rp], o[rq]
            o[rp] = c * arp - s * arq
            o[rq] = s * arp + c * arq
            for k in range(3):
                vkp, vkq = V[k][p], V[k][q]
                V[k][p] = c * vkp - s * vkq
                V[k][q] = s * vkp + c * vkq
    write_back()
    return w_out, V_out


def _svd3(F: np.ndarray):
    """Rotation-variant SVD in the (3, 3, N) layout; see ``rotation_variant_svd``."""
    w, Vm = _jacobi_eigh3(np.einsum("kie,kje->ije", F, F))
    w = [w[0], w[1], w[2]]
    v = [Vm[:, 0], Vm[:, 1], Vm[:, 2]]
    for a, b in ((0, 1), (1, 2), (0, 1)):  # sorting network, descending
        swap = w[a] < w[b]
        if swap.any():
            w[a], w[b] = np.where(swap, w[b], w[a]), np.where(swap, w[a], w[b])
            v[a], v[b] = np.where(swap, v[b], v[a]), np.where(swap, v[a], v[b])
    v[2] = v[2] * np.where((_cross(v[0], v[1]) * v[2]).sum(0) < 0.0, -1.0, 1.0)
    b = [np.einsum("ije,je->ie", F, vk) for vk in v]  # columns of F V
    s0 = np.sqrt((b[0] * b[0]).sum(0))
    u0 = b[0] / np.maximum(s0, _TINY)
    if not np.all(s0 > _TINY):  # F == 0: any frame works
        u0 = np.where(s0 > _TINY, u0, np.array([[1.0], [0.0], [0.0]]))
    b1 = b[1] - (u0 * b[1]).sum(0) * u0
    s1 = np.sqrt((b1 * b1).sum(0))
    u1 = b1 / np.maximum(s1, _TINY)
    u1 = u1 - (u0 * u1).sum(0) * u0  # second Gram-Schmidt pass
    u1 = u1 / np.maximum(np.sqrt((u1 * u1).sum(0)), _TINY)
    flat = ~(s1 > 1e-14 * s0 + _TINY)
    if flat.any():  # sigma_1 ~ 0 (element collapsed to a segment): complete the frame
        uf = u0[:, flat]
        k = np.argmin(np.abs(uf), axis=0)
        e = np.zeros_like(uf)
        e[k, np.arange(uf.shape[1])] = 1.0
        p = _cross(uf, e)
        u1[:, flat] = p / np.sqrt((p * p).sum(0))
    u2 = _cross(u0, u1)
    s2 = (u2 * b[2]).sum(0)
    U = np.stack([u0, u1, u2], axis=1)
    V = np.stack(v, axis=1)
    return U, np.stack([s0, s1, s2]), V


def rotation_variant_svd(F):
    """Rotation-variant SVD F = U diag(sigma) V^T of a batch of 3x3 matrices.

    det U = det V = +1; sigma_0 >= sigma_1 >= |sigma_2|, and sigma_2 < 0 iff
    det F < 0 (Irving et al. 2004; Teran et al. 2005).  V comes from a Jacobi
    eigen-decomposition of F^T F, U from a Gram-Schmidt QR of F V, completed
    to a rotation for flat or collapsed elements.

    Parameters
    ----------
    F : (N, 3, 3) ndarray or tensor.

    Returns
    -------
    U (N, 3, 3), sigma (N, 3), V (N, 3, 3), float64, of F's array type.
    """
    is_torch = isinstance(F, torch.Tensor)
    Fn = F.detach().cpu().numpy() if is_torch else np.asarray(F)
    Fs = np.ascontiguousarray(Fn.transpose(1, 2, 0), dtype=np.float64)
    U, s, V = _svd3(Fs)
    U, s, V = U.transpose(2, 0, 1), s.T, V.transpose(2, 0, 1)
    if is_torch:
        return torch.from_numpy(U.copy()), torch.from_numpy(s.copy()), torch.from_numpy(V.copy())
    return U, s, V


# --------------------------------------------------------------------------
# the energy term
# --------------------------------------------------------------------------
class StVKTets(EnergyTerm):
    """St. Venant-Kirchhoff energy of linear tetrahedra, sum_e W_e Psi(F_e).

    Parameters
    ----------
    rest_positions : (n, 3) tensor of rest vertex positions (its dtype is kept).
    tets : (E, 4) long tensor of vertex indices, positively oriented
        (det [X1-X0, X2-X0, X3-X0] > 0).
    youngs_modulus, poisson_ratio : floats or (E,) tensors.

    Attributes
    ----------
    stencils : (E, 4) vertex indices.
    Dm_inv : (E, 3, 3) inverse rest edge matrices.
    rest_volume : (E,) rest volumes W_e.
    grad_op : (E, 4, 3) D with F = sum_a x_a D_a^T, i.e. the (9, 12) map
        vec(F) = B x_e in factored form (see ``deformation_map``).
    mu, lam : Lame parameters, scalars or (E,) tensors.

    Raises
    ------
    ValueError if a rest volume is <= 0 or non-finite (the message names the
    element indices).
    """

    name = "stvk_tets"

    def __init__(self, rest_positions, tets, youngs_modulus, poisson_ratio):
        rest = torch.as_tensor(rest_positions)
        if not rest.is_floating_point():
            rest = rest.to(torch.float64)
        tets = torch.as_tensor(tets, dtype=torch.long, device=rest.device)
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise ValueError(f"tets must have shape (E, 4), got {tuple(tets.shape)}")
        self.stencils = tets
        self.rest_positions = rest
        Dm = _edge_matrix(rest, tets)
        vol = torch.linalg.det(Dm) / 6.0
        bad = torch.nonzero(~(torch.isfinite(vol) & (vol > 0)), as_tuple=False).flatten()
        if bad.numel():
            idx = bad[:10].tolist()
            more = f" (and {bad.numel() - 10} more)" if bad.numel() > 10 else ""
            raise ValueError(
                f"tets {idx}{more} have non-positive or non-finite rest volume "
                f"(first: element {idx[0]}, volume {vol[idx[0]].item():.3e}); "
                "inverted or degenerate rest tetrahedra"
            )
        self.rest_volume = vol
        self.Dm_inv = torch.linalg.inv(Dm)
        self.grad_op = torch.cat([-self.Dm_inv.sum(1, keepdim=True), self.Dm_inv], dim=1)
        mu, lam = lame(youngs_modulus, poisson_ratio)
        self.mu = torch.as_tensor(mu, dtype=rest.dtype, device=rest.device)
        self.lam = torch.as_tensor(lam, dtype=rest.dtype, device=rest.device)
        # float64 NumPy copies for the closed forms, element axis last
        E = tets.shape[0]

        def np64(t, shape=None):
            a = t.detach().cpu().numpy().astype(np.float64)
            if shape is None:  # (E, r, c) -> (r, c, E)
                return np.ascontiguousarray(a.transpose(1, 2, 0))
            return np.broadcast_to(a, shape).copy()

        self._D_soa = np64(self.grad_op)  # (4, 3, E)
        self._Dminv_soa = np64(self.Dm_inv)  # (3, 3, E)
        self._vol_np, self._mu_np, self._lam_np = np64(vol, (E,)), np64(self.mu, (E,)), np64(self.lam, (E,))
        self._work: dict[str, torch.Tensor] = {}  # cached work arrays of the closed forms

    def weighted_subset(self, index, weights) -> "StVKTets":
        """sum_{e in index} w_e W_e Psi(F_e) (a cubature, see ``base.subset_weights``).

        StVK is linear in (mu, lam) at a fixed Poisson ratio, so w_e W_e Psi is
        W_e Psi with Young's modulus w_e Y.
        """
        idx, w = subset_weights(index, weights, int(self.stencils.shape[0]))

        def per_element(t):
            t = torch.as_tensor(t, dtype=torch.float64)
            return t[idx] if t.ndim else t

        mu, lam = per_element(self.mu), per_element(self.lam)
        youngs = mu * (3.0 * lam + 2.0 * mu) / (lam + mu)
        nu = lam / (2.0 * (lam + mu))
        return StVKTets(self.rest_positions, self.stencils[idx], youngs * w, nu)

    # -- kinematics -------------------------------------------------------
    def _rest(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return t if (t.dtype == like.dtype and t.device == like.device) else t.to(like)

    def deformation_gradient(self, xe: torch.Tensor) -> torch.Tensor:
        """F = Ds Dm^{-1}; xe (..., E, 4, 3) -> (..., E, 3, 3)."""
        Ds = (xe[..., 1:, :] - xe[..., :1, :]).transpose(-1, -2)
        return Ds @ self._rest(self.Dm_inv, xe)

    def deformation_map(self) -> torch.Tensor:
        """Dense B (E, 9, 12) with vec(F) = B x_e (row-major vec, x_e = xe.reshape(E, 12)).

        B[e, 3i+j, 3a+c] = delta_ic D[e, a, j].
        """
        D = self.grad_op
        eye = torch.eye(3, dtype=D.dtype, device=D.device)
        B = eye[None, :, None, None, :] * D.transpose(1, 2)[:, None, :, :, None]  # (E, i, j, a, c)
        return B.reshape(D.shape[0], 9, 12)

    # -- energy and stress ------------------------------------------------
    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        """W_e Psi(F_e), Psi = mu ||E||_F^2 + lam/2 tr(E)^2, E = (F^T F - I)/2.

        xe : (..., E, 4, 3) -> (..., E); differentiable, batched.
        """
        F = self.deformation_gradient(xe)
        psi = stvk_density(F, self._rest(self.mu, xe), self._rest(self.lam, xe))
        return self._rest(self.rest_volume, xe) * psi

    def first_piola(self, x: torch.Tensor) -> torch.Tensor:
        """First Piola-Kirchhoff stress P = F (2 mu E + lam tr(E) I).

        x : (..., n, 3) -> (..., E, 3, 3).
        """
        F = self.deformation_gradient(self.gather(x))
        eye = torch.eye(3, dtype=F.dtype, device=F.device)
        Eg = 0.5 * (F.transpose(-1, -2) @ F - eye)
        trE = Eg.diagonal(dim1=-2, dim2=-1).sum(-1)
        mu = self._rest(self.mu, F)[..., None, None]
        lam = self._rest(self.lam, F)[..., None, None]
        S = 2.0 * mu * Eg + lam * trE[..., None, None] * eye
        return F @ S

    def stress_norm(self, x: torch.Tensor) -> torch.Tensor:
        """||P||_F per element; x (..., n, 3) -> (..., E)."""
        return torch.linalg.matrix_norm(self.first_piola(x))

    # -- closed-form derivatives -----------------------------------------
    def local_gradient_hessian(self, xe: torch.Tensor, project: bool = True):
        """Closed-form per-element gradient and Hessian.

        Parameters
        ----------
        xe : (E, 4, 3) element positions.
        project : if True (default) return W B^T (dP/dF)^+ B with dP/dF
            projected analytically in the principal-stretch frame (module
            docstring); else the exact Hessian W B^T (dP/dF) B.

        Returns
        -------
        g : (E, 12) = W B^T vec(P), H : (E, 12, 12); dtype/device of xe.
        Entries are ordered like ``xe.reshape(E, 12)``.  Computed in float64
        NumPy on the CPU; the term keeps work arrays between calls, so one
        instance must not be used from several threads at once.
        """
        x = xe.detach().cpu().numpy()
        n = x.shape[0]
        x = np.ascontiguousarray(x.transpose(1, 2, 0), dtype=np.float64)  # (4, 3, E)
        D, vol, mu, lam = self._D_soa, self._vol_np, self._mu_np, self._lam_np
        F = np.einsum("kie,kje->ije", x[1:] - x[:1], self._Dminv_soa)  # F = Ds Dm^-1
        C = np.einsum("kie,kje->ije", F, F)
        trE = 0.5 * (C[0, 0] + C[1, 1] + C[2, 2] - 3.0)
        S = mu * C  # S = 2 mu E + lam tr(E) I = mu C + (lam tr(E) - mu) I
        shift = lam * trE - mu
        for i in range(3):
            S[i, i] += shift
        P = np.einsum("ike,kje->ije", F, S)
        g = np.einsum("aje,cje->eac", D, P) * vol[:, None, None]  # W D P^T
        g = torch.from_numpy(g.reshape(n, 12))
        if project:
            H = self._projected_hessian(F, D, vol, mu, lam)
        else:
            H = self._exact_hessian(F, S, D, vol, mu, lam)
        return g.to(dtype=xe.dtype, device=xe.device), H.to(dtype=xe.dtype, device=xe.device)

    def _buffer(self, name: str, shape) -> torch.Tensor:
        """A cached float64 work array (re-used across calls: fresh multi-MB
        allocations cost more in page faults than the arithmetic)."""
        buf = self._work.get(name)
        if buf is None or tuple(buf.shape) != tuple(shape):
            buf = torch.zeros(shape, dtype=torch.float64)
            self._work[name] = buf
        return buf

    def _np_buffer(self, name: str, shape) -> np.ndarray:
        """NumPy view of a cached work array (see ``_buffer``)."""
        return self._buffer(name, shape).numpy()

    def _exact_hessian(self, F, S, D, vol, mu, lam):
        """W B^T (dP/dF) B, with
        dP_ij/dF_kl = d_ik S_lj + mu F_il F_kj + mu (F F^T)_ik d_jl + lam F_ij F_kl,
        and B^T = kron(D, I) (E, 12, 9) in the (j, i) ordering of vec(F)."""
        n = F.shape[-1]
        Ft = torch.from_numpy(np.ascontiguousarray(F.transpose(2, 0, 1)))  # (E, 3, 3)
        FtT = Ft.transpose(1, 2).contiguous()  # F^T
        StT = torch.from_numpy(np.ascontiguousarray(S.transpose(2, 1, 0)))  # S^T
        mu_t = torch.from_numpy(mu)[:, None, None]
        lam_t = torch.from_numpy(lam)[:, None, None]
        eye = torch.eye(3, dtype=torch.float64)
        Kd = self._work.get("Kd")
        if Kd is None:
            Dt = torch.from_numpy(np.ascontiguousarray(D.transpose(2, 0, 1)))
            Kd = (Dt[:, :, None, :, None] * eye[None, None, :, None, :]).reshape(n, 12, 9)
            self._work["Kd"] = Kd
        # C[e, j, i, l, k] = dP_ij / dF_kl
        C = self._buffer("C", (n, 3, 3, 3, 3))
        torch.mul(StT[:, :, None, :, None], eye[None, None, :, None, :], out=C)
        C.addcmul_((mu_t * Ft)[:, None, :, :, None], FtT[:, :, None, None, :])
        C.addcmul_((mu_t * (Ft @ FtT))[:, None, :, None, :], eye[None, :, None, :, None])
        C.addcmul_((lam_t * FtT)[:, :, :, None, None], FtT[:, None, None, :, :])
        C.mul_(torch.from_numpy(vol)[:, None, None, None, None])
        KC = self._buffer("KC", (n, 12, 9))
        torch.matmul(Kd, C.view(n, 9, 9), out=KC)
        # dP/dF is symmetric, so H is too (to round-off); a fresh array, callers keep it
        return KC @ Kd.transpose(1, 2)

    def _projected_hessian(self, F, D, vol, mu, lam):
        """W sum_k max(lambda_k, 0) g_k g_k^T over the 9 analytic eigenpairs of dP/dF.

        With g_pq = B^T vec(u_p v_q^T) = (D v_q) kron u_p, H = N^T N for the
        9 weighted mode vectors (rows of N (E, 9, 12)): the scaling modes
        sum_p L[p, k] g_pp with A^+ = L L^T (Cholesky where the 3x3 scaling
        block A is positive definite, eigen-clamped Jacobi elsewhere) and the
        flip/twist modes (g_ij +/- g_ji) sqrt(max(lambda, 0) / 2); everything
        times sqrt(W).
        """
        n = F.shape[-1]
        U, sig, V = _svd3(F)
        s2 = sig * sig
        T = 0.5 * (s2[0] + s2[1] + s2[2] - 3.0)
        sw = np.sqrt(vol)
        # scaling block A (Hessian of Psi(diag sigma) in sigma) and a factor L, A+ = L L^T
        A = lam * sig[:, None] * sig[None, :]
        for i in range(3):
            A[i, i] += mu * (3.0 * s2[i] - 1.0) + lam * T
        L = np.zeros((3, 3, n))
        with np.errstate(invalid="ignore", divide="ignore"):
            L[0, 0] = np.sqrt(A[0, 0])
            L[1, 0] = A[0, 1] / L[0, 0]
            L[2, 0] = A[0, 2] / L[0, 0]
            L[1, 1] = np.sqrt(A[1, 1] - L[1, 0] ** 2)
            L[2, 1] = (A[1, 2] - L[2, 0] * L[1, 0]) / L[1, 1]
            L[2, 2] = np.sqrt(A[2, 2] - L[2, 0] ** 2 - L[2, 1] ** 2)
        # fall back to the eigen-clamp where A is not (safely) positive definite
        bad = ~(np.minimum(np.minimum(L[0, 0], L[1, 1]), L[2, 2])
                > 1e-6 * np.sqrt(np.abs(A[0, 0]) + np.abs(A[1, 1]) + np.abs(A[2, 2])))
        if bad.any():
            alpha, W = _jacobi_eigh3(np.ascontiguousarray(A[:, :, bad]))
            L[:, :, bad] = W * np.sqrt(np.maximum(alpha, 0.0))[None, :, :]
        L *= sw
        # flip / twist eigenvalues for the pairs (0,1), (0,2), (1,2)
        i, j = [0, 0, 1], [1, 2, 2]
        base = mu * (s2[i] + s2[j] - 1.0) + lam * T
        cross = mu * sig[i] * sig[j]
        # mode vectors g_pq = B^T vec(u_p v_q^T) = (D v_q) kron u_p, (4, 3, E) arrays
        DV = np.einsum("aje,jpe->ape", D, V)  # DV[:, p] = D v_p
        N = self._np_buffer("N", (9, 4, 3, n))
        np.einsum("ape,pke,cpe->kace", DV, L, U, out=N[0:3])  # scaling: sum_p L[p, k] g_pp
        pi, qi = [0, 0, 1], [1, 2, 2]
        Gpq = DV[:, qi].transpose(1, 0, 2)[:, :, None, :] * U[:, pi].transpose(1, 0, 2)[:, None, :, :]
        Gqp = DV[:, pi].transpose(1, 0, 2)[:, :, None, :] * U[:, qi].transpose(1, 0, 2)[:, None, :, :]
        wf = np.sqrt(0.5 * np.maximum(base + cross, 0.0)) * sw
        wt = np.sqrt(0.5 * np.maximum(base - cross, 0.0)) * sw
        np.multiply(Gpq + Gqp, wf[:, None, None, :], out=N[3:6])  # flips
        np.multiply(Gpq - Gqp, wt[:, None, None, :], out=N[6:9])  # twists
        # H = N^T N per element, after one transposition to the (E, 9, 12) layout
        NE = self._buffer("NE", (n, 108))
        NE.copy_(torch.from_numpy(N.reshape(108, n)).T)
        NE = NE.view(n, 9, 12)
        return NE.transpose(1, 2) @ NE


__all__ = [
    "StVKTets",
    "lame",
    "lumped_masses",
    "rotation_variant_svd",
    "stvk_density",
    "tet_volumes",
]
