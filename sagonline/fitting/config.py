"""The fitting recipe's settings, one default each (registered as the Hydra schema `fit/schema`;
conf/scenes.yaml only overrides)."""

from __future__ import annotations

from dataclasses import dataclass

from sagonline.core.settings import check_settings

# What a recipe recorded before a setting existed ran with: that setting's default, but for the
# settings whose rule before them differed, where the fit behaved as these values do.
BEFORE_SETTINGS = {"view_near_quantile": 0.02, "backdrop": "fixed"}


def as_recorded(saved: dict, today: dict) -> dict:
    """A recorded recipe (fit_config.json, a checkpoint's) with each setting it predates filled
    in: `today`'s value (the defaults, as `asdict` or as JSON gives them), or the rule before the
    setting where that differed (`BEFORE_SETTINGS`)."""
    return today | BEFORE_SETTINGS | saved


@dataclass
class FitConfig:
    kind: str = "2dgs"
    """2dgs (surfels, the paper's) or 3dgs (ellipsoids)."""
    init: str = "auto"
    """Start points: auto (the capture's COLMAP points, else SIFT matches triangulated with the
    poses fixed, else random points in the frusta)."""
    sift_peak_threshold: float = 0.0066667
    """The SIFT detector's contrast threshold of the triangulated start points (COLMAP's
    default); lower finds features on dark or plain surfaces, where few start points fall."""
    guided_matching: bool = False
    """Match features again along each verified pair's epipolar geometry (more matches where
    texture is weak) for the triangulated start points."""
    background_points: int = 5000
    """Random points in the frusta, behind what sparse start points explain."""
    max_side: int = 228
    """Images downsampled so the longer side is at most this (`make scenes`)."""
    iterations: int = 3000
    """Training steps (the paper trains 30k on a GPU: fit=paper); CPU fits are for small
    scenes."""
    sh_degree: int = 3
    """Spherical-harmonics degree of the colours (0-3)."""
    init_points: int = 15000
    """Random start points when the capture has no points to start from."""
    lambda_dssim: float = 0.2
    """Weight of 1 - SSIM beside L1 in the photometric loss."""
    robust_trim: float = 0.0
    """The fraction of each view's pixels of largest residual left out of the photometric loss
    (`losses.photometric_loss`), from `robust_from` on: content no other photograph agrees
    with (a background that moved between photo sets, passers-by) stops pulling the fit; 0:
    off."""
    robust_from: int = 500
    """The iteration the trimmed loss starts at (before it, the residuals say little)."""
    lambda_aniso: float = 0.0
    """Weight of the needle penalty (`losses.anisotropy_penalty`); 0: off."""
    max_aspect: float = 10.0
    """Longest / shortest axis allowed before the needle penalty starts."""
    lambda_dist: float = 10.0
    """2DGS's depth distortion (`losses.depth_distortion`): gathers each ray's weight at one
    depth; 0: off. Chosen on mold_cape (docs/fitting.md): real masks voting, 85.2 -> 89.5 / 91.1
    mIoU on two seeds; 1 gave 88.3, 100 collapsed the fit (55.9)."""
    dist_from: int = 300
    """The iteration the depth distortion starts at (2DGS: 3000 of 30000)."""
    lambda_normal: float = 0.05
    """2DGS's normal consistency (`losses.normal_consistency`): surfel normals along the
    rendered depth's; 0: off."""
    normal_from: int = 700
    """The iteration the normal consistency starts at (2DGS: 7000 of 30000)."""
    lr_means: float = 1.6e-4
    """Learning rate of the centres, times the scene extent, decayed to 1% by the end."""
    lr_scales: float = 5e-3
    """Learning rate of the log scales."""
    lr_quats: float = 1e-3
    """Learning rate of the rotations."""
    lr_opacity: float = 5e-2
    """Learning rate of the opacity logits."""
    lr_sh: float = 2.5e-3
    """Learning rate of the SH degree 0; higher degrees learn 20x slower (as 3DGS)."""
    camera_clearance: float | None = None
    """Prune Gaussians this close to any camera centre; 0: off; None: the caller's automatic
    value (`make scenes`: half the nearest recorded depth), off when none is given."""
    view_clearance: float = 0.85
    """Prune Gaussians whose 3-sigma footprint reaches into a view nearer than this fraction of
    the nearest depth recorded for that view (LLFF bounds, else the start points' depths); 0:
    off. The floaters that hide the object in views between the photographs sit there. Chosen
    on mold_cape (docs/fitting.md): real masks voting 89.5 / 91.1 -> 94.8 / 94.6."""
    view_near_quantile: float = 0.01
    """The quantile of the start points' depths inside a photographed view that bounds its
    recorded near depth (with the LLFF bound, the smaller wins): the view clearance prunes what
    stands nearer than `view_clearance` x that depth (pose-only views keep 0.02). At 0.02 (the
    rule before this setting) the depth lay beyond mother_child's statuette in three training
    views, whose heads are fewer than 2% of those views' points, and the clearance pruned them:
    real masks 81.55 -> 89.35 over three fits; on the three other captures 0.01 moves no near
    depth the fit reads (their fits are the same). Chosen leave-one-capture-out
    (docs/real_captures.md)."""
    view_clearance_views: str = "train"
    """train: the training photographs' recorded depths; all: every pose's."""
    pose_view_clearance: float = 0.5
    """After the last iteration, prune Gaussians whose 3-sigma footprint reaches into a pose-only
    view (a camera of the capture without a photograph) nearer than this fraction of that
    view's recorded near depth; 0: off. Lower than `view_clearance` because those views' near
    depths are the start points', not the photographs' own: at 0.85 in every view the object's
    own surfels went (duck_queen 88.8 -> 82.6 mIoU); at 0.5 the floaters in front of
    mask-only views go and the object stays (docs/real_captures.md: all three captures)."""
    carve_views: int = 0
    """After the fit, drop the Gaussians that at least this many training photographs look
    through: the centre in the view's image, nearer by more than `carve_margin` than the
    surface the fit renders there, which is opaque (alpha > 0.5). The photograph saw past that
    point, so nothing is there; such Gaussians explain at most the one or two photographs that
    see them and stand in front of the object between photographs (`strategy.looked_through`).
    Then `polish_iterations` close the holes; 0: off."""
    carve_margin: float = 0.1
    """How much nearer than the rendered surface (a fraction of its depth) a looked-through
    centre must be."""
    polish_iterations: int = 300
    """With `carve_views` or `polish_opacity_entropy`: iterations trained after the last one
    (after the carve), without densification, the positions at their last learning rate (the
    surfaces behind close what the carve opened)."""
    polish_opacity_entropy: float = 0.0
    """Weight of the opacities' binary entropy in the polish (`losses.opacity_entropy`): each
    opacity is pushed to 0 or 1, and the ones that end below `prune_opacity` are dropped. A
    half-transparent surface lets what lies behind it show through and vote for the object in
    the views between photographs; after the polish a surface is there or not; 0: off."""
    co_prune_seed: int | None = None
    """After the last iteration, drop the Gaussians whose 3-sigma footprint holds no centre
    of a second draw of the recipe (`finish_from`'s fit of this seed), then polish: where the
    photographs leave depth open, two draws put their surfaces at different depths, so what
    one draw has alone is not what the photographs agree on (co-pruning, CoR-GS, Zhang et al.
    2024). It needs both draws fitted (twice the fitting); None: off."""
    co_prune_sigmas: float = 3.0
    """The co-pruning's reach: this many times each Gaussian's largest scale."""
    lambda_warp: float = 0.0
    """Weight of the neighbour consistency (`losses.neighbour_consistency`): each pixel moved
    to its rendered depth must show the colour the two nearest training photographs show
    there, so surfaces drawn in front of what the photographs agree on are pulled back; 0:
    off."""
    warp_from: int = 500
    """The iteration the neighbour consistency starts at (the depth means little before)."""
    lambda_depth: float = 0.0
    """Weight of the monocular depth prior (`depth_prior.depth_correlation`): each training
    view's rendered depth must order near and far as a single-image depth network orders its
    photograph (up to scale and shift), so a surface one photograph placed in front of the
    object, which the photometric loss cannot tell from the right one, is pulled back; 0: off.
    Screened at 0.05 on the sparse protocol (docs/fitting.md): +2 to +13 points on two captures,
    -4 to -14 on the two where the network's depth is wrong, so off; its guarded forms
    (`depth_patch`, `depth_pool`, `depth_trust`) lose the gains with the harm."""
    depth_patch: int = 32
    """The side in pixels of the tiles over which `lambda_depth` also correlates the two depths
    (each surface against what surrounds it), averaged with the whole view's correlation; 0:
    the whole view only (near against far: a network's coarse depth orders a view's surfaces
    more reliably than it shapes each one)."""
    depth_trust: bool = False
    """With `lambda_depth`: weight each view's and tile's term by the correlation the fit
    already has with the network there (clamped at 0, no gradient), so a network that misreads
    a view is ignored there instead of fought (`depth_prior.trusted`)."""
    depth_pool: int = 1
    """With `lambda_depth`: compare the two depths averaged over blocks of this many pixels a
    side (the detail the network resolves; `depth_prior.pooled`); 1: pixel by pixel."""
    depth_model: str = "weights/fastdepth/fastdepth.onnx"
    """The ONNX depth network of `lambda_depth` (FastDepth, fetched by `make weights`)."""
    depth_pseudo_every: int = 0
    """With `lambda_depth`: every n-th step also renders a view between two neighbouring
    training photographs and asks its depth to follow the network's depth of that render
    (`depth_prior.pseudo_view_term`); 0: off."""
    depth_pseudo_from: int = 500
    """The iteration the pseudo views start at (before it, the render shows little)."""
    densify_from: int = 200
    """The iteration densification starts at."""
    densify_until: int = 1500
    """The iteration densification stops at."""
    densify_every: int = 100
    """Iterations between densification (and pruning) steps."""
    grad_threshold: float = 2e-4
    """A Gaussian whose mean screen-space gradient exceeds this is cloned or split."""
    percent_dense: float = 0.01
    """Gaussians smaller than this fraction of the scene extent are cloned, larger ones split."""
    max_gaussians: int = 40_000
    """Densification stops adding Gaussians at this count."""
    opacity_reset_every: int = 1000
    """Iterations between opacity resets (3DGS's trick against floaters)."""
    prune_opacity: float = 0.005
    """Gaussians below this opacity are pruned."""
    opacity_decay: float = 1.0
    """Every opacity is multiplied by this after each step of the densification phase (until
    `densify_until`), so a Gaussian stays only while the photographs keep pulling it up; the
    ones no photograph needs fade below `prune_opacity` and are pruned (the opacity decay of
    sparse-view Gaussian splatting, Han et al. 2024). 1: off."""
    holdout_every: int = 8
    """Every n-th photograph is held out of the fit (its PSNR is the held-out PSNR)."""
    train_every: int = 1
    """Fit from every n-th of the photographs not held out (in name order); the others are
    neither fitted nor held out. 1: all of them; 2: the sparse-photograph protocol (half the
    photographs, the same held-out ones: `docs/fitting.md`)."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The render's background colour during the fit (and the evaluation's renders of it)."""
    backdrop: str = "detect"
    """detect: the fit renders on white where the photographs show a white backdrop
    (`capture.white_backdrop`: a studio sweep or turntable; 3DGS's --white_background), else on
    `background`; fixed: always on `background`. On white the backdrop needs no surfaces, so a
    backdrop that moved against the object between photo sets leaves none in front of it
    (mary_rose, docs/real_captures.md)."""
    random_background: bool = False
    """Each training step renders on a colour drawn for that step (seeded by seed and step)
    instead of `background`, so no pixel of a photograph can be matched by letting the
    background show through: a dark object over a black background is otherwise fitted as a
    half-transparent surface, through which what lies behind it votes in the views between
    photographs. Not where the fit renders on a detected backdrop (`backdrop`): there the
    backdrop's colour is what the photographs show. The renders after the fit use
    `background`."""
    checkpoint_every: int = 100
    """Iterations between checkpoints (an interrupted fit resumes from the last)."""
    time_budget_s: float | None = None
    """Seconds; None: bounded by iterations alone (reproducible)."""
    seed: int = 0
    """Seeds the start points, the densification noise and the held-out split's order."""
    device: str = "cpu"
    """cpu (the compiled kernel) or cuda (gsplat)."""
    backend: str = "auto"
    """auto: gsplat on CUDA, the compiled kernel on the CPU, else PyTorch (a fit needs gradients,
    so on CUDA without gsplat it renders with PyTorch, never the Triton walk)."""

    def __post_init__(self) -> None:
        self.background = tuple(self.background)  # Hydra hands lists in
        budget = self.time_budget_s
        check_settings(
            "fit",
            kind=(self.kind in ("2dgs", "3dgs"), self.kind, "2dgs or 3dgs"),
            iterations=(self.iterations >= 1, self.iterations, ">= 1"),
            max_side=(self.max_side >= 8, self.max_side, ">= 8 pixels"),
            sh_degree=(0 <= self.sh_degree <= 3, self.sh_degree, "0, 1, 2 or 3"),
            max_gaussians=(self.max_gaussians >= 1, self.max_gaussians, ">= 1"),
            train_every=(self.train_every >= 1, self.train_every, ">= 1"),
            sift_peak_threshold=(
                0 < self.sift_peak_threshold < 1,
                self.sift_peak_threshold,
                "in (0, 1)",
            ),
            opacity_decay=(0 < self.opacity_decay <= 1, self.opacity_decay, "in (0, 1]"),
            time_budget_s=(budget is None or budget >= 0, budget, ">= 0 seconds, or null"),
            view_clearance=(self.view_clearance >= 0, self.view_clearance, ">= 0"),
            view_near_quantile=(
                0 <= self.view_near_quantile < 1,
                self.view_near_quantile,
                "a fraction in [0, 1)",
            ),
            pose_view_clearance=(
                0 <= self.pose_view_clearance <= 1,
                self.pose_view_clearance,
                "in [0, 1]",
            ),
            lambda_dist=(self.lambda_dist >= 0, self.lambda_dist, ">= 0"),
            lambda_normal=(self.lambda_normal >= 0, self.lambda_normal, ">= 0"),
            lambda_warp=(self.lambda_warp >= 0, self.lambda_warp, ">= 0"),
            lambda_depth=(self.lambda_depth >= 0, self.lambda_depth, ">= 0"),
            depth_patch=(self.depth_patch >= 0, self.depth_patch, ">= 0 pixels"),
            depth_pool=(self.depth_pool >= 1, self.depth_pool, ">= 1 pixel"),
            depth_pseudo_every=(self.depth_pseudo_every >= 0, self.depth_pseudo_every, ">= 0"),
            carve_views=(self.carve_views >= 0, self.carve_views, ">= 0"),
            carve_margin=(0 <= self.carve_margin < 1, self.carve_margin, "a fraction in [0, 1)"),
            polish_iterations=(self.polish_iterations >= 0, self.polish_iterations, ">= 0"),
            co_prune_seed=(
                self.co_prune_seed is None or self.co_prune_seed >= 0,
                self.co_prune_seed,
                "null or a seed >= 0",
            ),
            co_prune_sigmas=(self.co_prune_sigmas > 0, self.co_prune_sigmas, "> 0"),
            polish_opacity_entropy=(
                self.polish_opacity_entropy >= 0,
                self.polish_opacity_entropy,
                ">= 0",
            ),
            lambda_dssim=(0 <= self.lambda_dssim <= 1, self.lambda_dssim, "in [0, 1]"),
            robust_trim=(0 <= self.robust_trim < 1, self.robust_trim, "a fraction in [0, 1)"),
            backdrop=(self.backdrop in ("fixed", "detect"), self.backdrop, "fixed or detect"),
        )
