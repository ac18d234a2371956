"""Small systems shared by the tests (SI units)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from sfem_filters import fem
from sfem_filters.fem.material import Material, Parameterisation
from sfem_filters.fem.mesh import TriMesh, delaunay_mesh, rectangle_mesh
from sfem_filters.fem.observation import node_observation_matrix
from sfem_filters.filtering import LinearGaussianModel
from sfem_filters.model import SFEMModel


def random_material(rng, n, E_range=(3e4, 2e5), nu_range=(0.2, 0.49)) -> Material:
    E = np.exp(rng.uniform(*np.log(E_range), n))
    return Material(E, rng.uniform(*nu_range, n))


def random_block_mesh(rng, n_interior=6, size=0.02) -> TriMesh:
    """Delaunay mesh of a square's corners, edge midpoints and random interior points
    (redrawn, deterministically from rng, until no interior triangle is a sliver)."""
    s = size
    ring = [(0, 0), (s / 2, 0), (s, 0), (s, s / 2), (s, s), (s / 2, s), (0, s), (0, s / 2)]
    while True:
        inner = rng.uniform(0.15 * s, 0.85 * s, (n_interior, 2))
        try:
            return delaunay_mesh(np.vstack([ring, inner]), min_angle_deg=1.0)
        except ValueError:
            continue


def small_model(rng, mesh=None, parameterisation="per_element", n_frames=5, alpha=10.0, beta=1e-3,
                noise=1e-5, jacobian="modal", material=None) -> SFEMModel:
    """Bottom edge fixed, random loads on every free dof, all non-fixed nodes observed."""
    mesh = mesh or random_block_mesh(rng)
    bottom = mesh.nodes_where(lambda x, y: y < 1e-12)
    fixed = fem.node_dofs(bottom)
    loads = rng.standard_normal((n_frames, mesh.n_dofs)) * 20.0
    observed = np.setdiff1d(np.arange(mesh.n_nodes), bottom)
    D = node_observation_matrix(mesh, observed)
    material = material or random_material(rng, mesh.n_elements)
    param = parameterisation
    if parameterisation == "per_element":
        param = Parameterisation.per_element(mesh.n_elements)
    return SFEMModel(mesh, material, loads, D, 0.01, fixed, density=1050.0, alpha=alpha, beta=beta,
                     measurement_std=noise, process_std=(1e-6, 1e-4), initial_std=(1e-5, 1e-4),
                     parameterisation=param, jacobian=jacobian)


def reduced_matrices(model, material=None):
    """Dense M and K over the free dofs of a model."""
    mat = material or model.material
    K = model.dofmap.restrict_matrix(fem.stiffness_matrix(model.mesh, mat.E, mat.nu)).toarray()
    return model.M, K


def two_identical_squares() -> TriMesh:
    """Two disconnected identical squares: every natural frequency is exactly repeated."""
    a = rectangle_mesh(0.01, 0.01, 3, 3)
    nodes = np.vstack([a.nodes, a.nodes + [0.02, 0.0]])
    return TriMesh(nodes, np.vstack([a.elements, a.elements + a.n_nodes]))


def simulate(model, rng, noise):
    """Truth from the model's own material and noisy observations."""
    system = model.system(model.theta_of(model.x0) if model.estimates_material else None)
    x = np.zeros(model.dim_x)
    w = model.dofmap.restrict(model.loads)
    ys = []
    for t in range(model.n_frames):
        if t > 0:
            x = system.step(x, w[t])
        ys.append(model.hx(np.concatenate([x, model.x0[model.dim_x:]]), t))
    ys = np.array(ys)
    return ys + rng.standard_normal(ys.shape) * noise


def ring(shape=(48, 48), centre=(23.5, 23.5), r_in=8.0, r_out=13.0, bump=0.0, angle=0.0):
    """A ring mask; ``bump`` adds a 3-lobed wobble to both radii (so the shape has features)."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    dx, dy = xx - centre[0], yy - centre[1]
    th = np.arctan2(dy, dx) - angle
    r = np.hypot(dx, dy)
    w = 1.0 + bump * np.cos(3 * th)
    return (r >= r_in * w) & (r <= r_out * w)


class BiasModel(LinearGaussianModel):
    """x_{t+1} = A x_t + G theta + w_t: linear in (x, theta), so the joint 'EKF' is exact."""

    def __init__(self, A, G, H, Q, R, P0, P3, n_frames, theta0):
        p = G.shape[1]
        zero = np.zeros((p,) + A.shape)
        super().__init__(lambda th: (A, zero), H, Q, R, np.zeros(len(A)), P0, n_frames, theta0, P3)
        self._A, self._G = A, G

    def fx(self, z, t):
        x, th = z[: self.n_restart], z[self.n_restart:]
        return np.concatenate([self._A @ x + self._G @ th, th])

    def F_jacobian(self, z, t):
        F = np.eye(self.dim_state)
        F[: self.n_restart, : self.n_restart] = self._A
        F[: self.n_restart, self.n_restart:] = self._G
        return F


def bias_model(rng, n, p, m, frames):
    """A random stable BiasModel and its data (theta_true drawn from N(0, I))."""
    A = rng.standard_normal((n, n))
    A *= 0.9 / max(abs(np.linalg.eigvals(A)))
    G = 0.3 * rng.standard_normal((n, p))
    H = rng.standard_normal((m, n))
    Q = np.diag(rng.uniform(0.01, 0.1, n))
    R = np.diag(rng.uniform(0.05, 0.2, m))
    B = rng.standard_normal((p, p))
    P3 = B @ B.T / p + 0.5 * np.eye(p)
    model = BiasModel(A, G, H, Q, R, 0.1 * np.eye(n), P3, frames, rng.standard_normal(p))
    theta_true = rng.standard_normal(p)
    x = np.zeros(n)
    y = np.empty((frames, m))
    for t in range(frames):
        if t:
            x = A @ x + G @ theta_true + rng.multivariate_normal(np.zeros(n), Q)
        y[t] = H @ x + rng.multivariate_normal(np.zeros(m), R)
    return model, y


def write_dicom(path, stored, trigger_ms, instance, slope=2.0, intercept=-4096.0, comments=None, spacing=1.75,
                acquisition_matrix=None):
    """One MR image as a scanner exports it: ``stored`` (H, W) 12-bit integers with RescaleSlope and
    RescaleIntercept, TriggerTime (ms), InstanceNumber, PixelSpacing (mm) and, when given,
    ImageComments (which DENSE exports use to tell their series apart) and AcquisitionMatrix
    (frequency rows, frequency columns, phase rows, phase columns)."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, MRImageStorage, generate_uid
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = MRImageStorage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = MRImageStorage, meta.MediaStorageSOPInstanceUID
    ds.Modality = "MR"
    ds.Rows, ds.Columns = np.shape(stored)
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    ds.PixelSpacing = [spacing, spacing]
    ds.TriggerTime, ds.InstanceNumber = float(trigger_ms), instance
    ds.RescaleSlope, ds.RescaleIntercept = slope, intercept
    if comments is not None:
        ds.ImageComments = comments
    if acquisition_matrix is not None:
        ds.AcquisitionMatrix = [int(v) for v in acquisition_matrix]
    ds.PixelData = np.asarray(stored, np.uint16).tobytes()
    ds.save_as(path, enforce_file_format=True)


def thickening_ring_tracks(mask, frames=6, noise_px=0.05, seed=0, turn=0.02):
    """Lagrangian tracks (px) of every pixel of ``mask`` (a ring) that dilates radially inward,
    u_r = -k(t) / r (area preserving: the wall thickens), and turns by ``turn`` rad per unit of t,
    with white noise of ``noise_px``. Returns ``(tracks, noise-free displacement (F, P, 2))``."""
    from sfem_filters.imaging.dense import LagrangianDisplacement, reference_points
    from sfem_filters.imaging.strain import mask_centre
    X = reference_points(mask)
    d = X - mask_centre(mask)
    t = np.linspace(0.2, 1.0, frames)
    rng = np.random.default_rng(seed)
    r = np.linalg.norm(d, axis=1)
    u_r = -(0.15 * t[:, None]) * (20.0 / r)[None]
    rot = np.column_stack([-d[:, 1], d[:, 0]])
    disp = u_r[..., None] * (d / r[:, None])[None] + turn * t[:, None, None] * rot[None]
    noisy = disp + noise_px * rng.standard_normal(disp.shape)
    tracks = LagrangianDisplacement(points=X, displacement=noisy, sd=np.full(disp.shape, noise_px),
                                    confidence=np.ones(disp.shape[:2]),
                                    frame_times_s=0.0225 + 0.015 * np.arange(frames), n_untracked=0,
                                    noise_sd=np.array([1.0, 1.0]))
    return tracks, disp


def write_case_frames(src, dst, frames: int, stride: int = 1):
    """Write the DENSE-Sim case folder ``src`` into the new folder ``dst`` at frames ``0, stride, ...``
    (``frames`` of them), every file cut as the case is published: the images and the truth per frame,
    the masks and ``config.yaml``'s ``tt`` with the reference (index 0) before them. Returns ``dst``."""
    dst = Path(dst)
    dst.mkdir(parents=True)
    keep = np.arange(frames) * stride
    for name in ("phase_x", "phase_y", "magnitude", "GT_Ecc", "GT_Err"):
        np.save(dst / f"{name}.npy", np.load(f"{src}/{name}.npy")[keep])
    np.save(dst / "LV_mask_time_lowres.npy", np.load(f"{src}/LV_mask_time_lowres.npy")[np.r_[0, keep + 1]])
    with open(f"{src}/config.yaml") as f:
        config = yaml.safe_load(f)
    config["sim_params"]["tt"] = [config["sim_params"]["tt"][i] for i in np.r_[0, keep + 1]]
    config["sim_params"]["Nt"] = frames
    with open(dst / "config.yaml", "w") as f:
        yaml.safe_dump(config, f)
    return dst


def count_calls(monkeypatch, module, name: str) -> list:
    """Replace ``module.name`` (looked up at call time by the code under test) with a wrapper that records each
    call; returns the list it appends to, so a test can see how much work a run did (e.g. that a resumed run
    did not start over)."""
    real = getattr(module, name)
    calls = []

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)
    monkeypatch.setattr(module, name, counted)
    return calls
