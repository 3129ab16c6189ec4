"""Named sets of numbers for the PBR-SR optimiser.

``paper`` reproduces every default of the paper (../shared/docs/METHOD.md, "Defaults the paper
gives"). The CPU presets ``fast`` / ``balanced`` / ``quality`` keep the paper's losses and
lambdas except a weaker pixel term (lambda_pix 1: the pseudo-GT of a small prior carries little
true detail), back-project the exported colour and data maps onto their LR maps
(``project_lr``), and change how much work is done and how the pixel target is made: fewer
views chosen for texel coverage (several views per texel) instead of a fixed sphere, a render
resolution that follows texel density (one pixel ~ one HR texel, capped), fewer iterations with
a larger Adam step, and the "detail" pseudo-GT (see ``PbrsrConfig.target``). The comments below
give the measurements behind each number (docs/METHOD.md has them in context);
``pbrsr bench upscale`` measures the presets themselves (docs/BENCHMARKS.md)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Literal

from ..errors import InvalidOptions

MAP_NAMES = ("base_color", "emissive", "normal", "occlusion", "roughness", "metallic")
MAP_KINDS = ("colour", "data", "normal")


@dataclass(frozen=True)
class PbrsrConfig:
    """Every number of one PBR-SR run (see the module docstring for how presets differ)."""

    name: str = "custom"
    # --- views --------------------------------------------------------------------------
    view_mode: Literal["orbit", "coverage"] = "coverage"
    """orbit: the fixed n_elev x n_azim sphere (the paper); coverage: greedily chosen from
    ``n_candidates`` sphere views for new texels (views.py)."""
    n_elev: int = 15
    n_azim: int = 50
    elev_range_deg: tuple[float, float] = (-60.0, 60.0)
    distance: float = 3.25
    """Camera distance around the mesh normalised to unit size (largest extent 1)."""
    fov_deg: float = 10.0
    n_candidates: int = 96
    """coverage mode: candidate views on a Fibonacci sphere."""
    max_views: int = 24
    """coverage mode: at most this many views are kept."""
    views_per_texel: int = 1
    """coverage mode: a texel counts as covered once this many chosen views see it."""
    min_new_texels: float = 0.002
    """coverage mode: stop adding views once the best adds less than this fraction of the
    texels (per image, averaged)."""
    # --- resolution -----------------------------------------------------------------------
    render_res: int | None = 1024
    """Pseudo-GT / optimisation render side in pixels; None = from texel density."""
    min_render_res: int = 64
    max_render_res: int = 1024
    texel_footprint: float = 1.0
    """Texel-density rule: aim for this many HR texels per pixel (median over covered
    pixels); 1.0 = one pixel per HR texel."""
    # --- prior ---------------------------------------------------------------------------
    check_prior: tuple[str, ...] = ()
    """Map kinds (colour, data, normal) on which the prior is checked against bicubic one
    scale down (prior/selfcheck.py) before it initialises a map of ``prior_maps``: a map (a
    data map's channel) where it loses starts from bicubic, and when it loses on every map the
    pseudo-GT uses bicubic too. Empty: never checked (the paper always uses its prior)."""
    normal_pick_max_scale: int | None = None
    """Normal maps upscaled by at most this factor, when the prior offers several candidates
    for them and ``check_prior`` does not name normal maps, are checked one scale down among
    those candidates alone (prior/selfcheck.py ``pick_only``): the closest upscales the map,
    never bicubic, whatever the flat rule says. Larger factors, and None: the prior's first
    candidate (its normal network) upscales every normal map."""
    prior_maps: tuple[str, ...] = ("base_color", "emissive")
    """Maps the prior initialises (names as in ``map_lr``; the paper: albedo and emissive);
    every other map, and every other channel of a packed ORM image, starts from bicubic
    interpolation."""
    max_prior_scale: int | None = None
    """The prior upscales by at most this factor (e.g. 2 of x4), or by the larger factor one
    pass of its network makes (a stride-4 texture network: x4; a pass at the input's size
    costs about the same whatever its stride), and bicubic interpolation does the rest, then
    one back-projection step onto its input (prior/direct.py ``upscale_rgb``): in the init,
    in the self-check (which scores the same upscaling) and in the pseudo-GT. None: the prior
    does the whole scale (the paper)."""
    self_ensemble: int = 1
    """The prior runs on this many symmetric copies of each map (1, 2, 4 or 8: the identity,
    the half turn, the quarter turns, the mirrors), each output turned back and the copies
    averaged (prior/symmetry.py): in the self-check, the blends and the init, one prior run
    per copy; the pseudo-GT's renders go through the prior once. 1: the prior once."""
    self_ensemble_by_kind: dict[str, int] = field(default_factory=dict)
    """Copies of ``self_ensemble`` per map kind (colour, data, normal) for the kinds named:
    ``{"normal": 2}`` averages normal maps over two copies and the others over
    ``self_ensemble``."""
    self_ensemble_max_scale: int | None = None
    """Maps upscaled by more than this factor run the prior once, whatever ``self_ensemble``
    and ``self_ensemble_by_kind`` say. None: the copies are made at every scale."""
    blend_data: bool = False
    """Each channel of a data map is a blend of the prior's candidates, bicubic and, for a
    metallic-roughness map's roughness and metallic, the upscale guided by the material's
    colour map (prior/guided.py), weighted by a least-squares fit one scale down
    (prior/blend.py); only when the check covers data maps (``check_prior``). Off: each
    channel takes the check's pick. The paper upscales each map on its own."""
    blend_margin: float = 0.0
    """With ``blend_data``: dB (one scale down) by which a data channel's blend must beat
    bicubic to be used; otherwise the channel keeps bicubic's upscale (prior/blend.py)."""
    blend_network_db: float = 0.1
    """With ``blend_data``: dB (one scale down, summed over a map's blended channels) a
    candidate network must add to the blends to run on the map at all: the work follows what
    the map gains from it (prior/blend.py)."""
    blend_channel_db: float | None = None
    """With ``blend_data``: dB (one scale down) a network left on a map must add to a
    channel's blend to run on that channel: each channel it is left out of saves one
    network run (prior/blend.py). None: it runs on every channel its fit weighs."""
    blend_pick_db: float | None = None
    """With ``blend_data``: dB (one scale down) by which a data channel's blend must beat the
    self-check's pick, where that pick beats bicubic, to replace it; otherwise the channel
    takes the pick (prior/blend.py). None: the blend is weighed against bicubic only."""
    blend_pick_floor: bool = False
    """With ``blend_data``: a candidate network stays in a data map's blends wherever leaving
    it out would put a channel's blend below the self-check's pick one scale down, whatever
    ``blend_network_db`` says (prior/blend.py)."""
    reach_db: float | None = None
    """A map of ``prior_maps`` whose render error, measured one scale down on the LR asset,
    lies this many dB or more below that of all the asset's maps together keeps bicubic's
    upscale: the renders do not show it (render_reach.py; direct follows balanced's). None:
    not measured, the prior runs on every map of ``prior_maps``."""
    deblock_jpeg: bool = False
    """LR maps stored as JPEG have their block artefacts reduced with the file's own
    quantisation tables (every component of 4:4:4 files; the luma of chroma-subsampled ones,
    their chroma rebuilt from it) before they become the init and the consistency target
    (asset/jpeg.py). The paper takes
    the LR maps as they are."""
    check_storage: bool = False
    """The self-check models a JPEG map's storage one scale down: the downscaled crop is
    compressed with the file's own tables and chroma sampling (and deblocked with them under
    ``deblock_jpeg``) before each candidate upscales it, as the LR map itself was stored
    (asset/jpeg.py ``stored_as``). Off: the crop as the protocol's degradation leaves it."""
    detail_gain: float = 0.0
    """Share (0 to 1) of the self-check's detail gain taken: a checked colour or data map's
    upscale departs from bicubic's by ``1 + detail_gain (k - 1)`` times the prior's
    departure, ``k`` the least-squares scale of that departure one scale down, per channel
    entry, within [0.5, 1.5] (prior/selfcheck.py ``detail_gain``); blends take their pick's.
    0: the prior's upscale as it is (the paper)."""
    # --- pseudo-GT -------------------------------------------------------------------------
    lr_render: Literal["supersample", "raster"] = "supersample"
    """How the LR render handed to the prior is made: area-averaged from the HR render
    (antialiased, like a mip-mapped rasteriser) or rasterised at LR size (one sample per
    pixel). On the 512 demo asset at x4 (one 512x512 view, rrdn-thick), the pseudo-GT's PSNR
    against the render of the GT maps was 26.5 dB supersampled vs 24.7 dB rasterised."""
    pseudo_gt_prior: str | None = None
    """The prior that upscales the LR renders into the pseudo-GT; None: the run's prior.
    ``bicubic`` with ``target`` "detail" makes the target the HR render of the init maps
    (the direct result's renders)."""
    pseudo_gt_self_ensemble: int = 1
    """The pseudo-GT's prior runs on this many symmetric copies of each LR render (1, 2, 4 or
    8, as ``self_ensemble`` for the maps), one prior run per copy and view. 1: once."""
    target: Literal["prior", "detail"] = "prior"
    """prior: the prior's output is the target (the paper); detail: the HR render of the init
    maps plus what the prior adds over bicubic (keeps exact silhouettes and shading)."""
    project_lr: tuple[str, ...] = ()
    """Map kinds (colour, data, normal) whose optimised HR maps get one back-projection step
    onto their LR maps before export (prior/backproject.py), on the maps (data-map channels)
    a back-projecting prior initialised: what the optimiser moved away from the LR model is
    put back. The paper exports the optimised maps as they are."""
    # --- optimisation ---------------------------------------------------------------------
    iterations: int = 2000
    batch_views: int = 4
    lr: float = 1e-4
    map_lr: dict[str, float] = field(default_factory=dict)
    """Factor on ``lr`` per map (base_color, emissive, normal, occlusion, roughness,
    metallic); maps not named use ``lr``. 0 keeps a map at its init."""
    lr_weight_maps: float | None = None
    """Adam step of the per-view weight maps; None = ``lr`` (the paper uses one lr)."""
    sampling: Literal["views", "pixels"] = "views"
    """views: each step renders ``batch_views`` whole views (the paper); pixels: each step
    shades ``pixels_per_step`` random covered pixels drawn across all views."""
    pixels_per_step: int = 65536
    weight_map_res: int = 64
    mask_unseen: bool = True
    """Texels no training view sees keep their init (their gradient is zeroed)."""
    # --- losses (paper 3.5) ---------------------------------------------------------------
    lambda_pix: float = 100.0
    lambda_reg: float = 0.5
    lambda_ssim: float = 10.0
    lambda_pbr: float = 10.0
    lambda_tv: float = 0.5
    w_metallic: float = 0.1
    w_other: float = 1.0

    # --- bookkeeping ----------------------------------------------------------------------
    gbuffer_cache_mb: int = 2048
    """G-buffers kept in memory (LRU); views beyond are rasterised again when used."""
    log_every: int = 10
    eval_views: int = 240
    """Evaluation views the benchmark uses (the paper's 6 x 40); not used in training."""

    def __post_init__(self) -> None:
        checks = [
            (self.iterations >= 0, "iterations must be >= 0"),
            (self.batch_views >= 1, "batch_views must be >= 1"),
            (self.lr > 0, "lr must be > 0"),
            (self.weight_map_res >= 1, "weight_map_res must be >= 1"),
            (self.pixels_per_step >= 1, "pixels_per_step must be >= 1"),
            (self.n_elev >= 1 and self.n_azim >= 1, "n_elev and n_azim must be >= 1"),
            (self.max_views >= 1 and self.n_candidates >= 1, "view counts must be >= 1"),
            (0 < self.fov_deg < 180, "fov_deg must be in (0, 180)"),
            (self.distance > 0, "distance must be > 0"),
            (self.render_res is None or self.render_res >= 8, "render_res must be >= 8"),
            (8 <= self.min_render_res <= self.max_render_res, "bad min/max render resolution"),
            (self.log_every >= 1, "log_every must be >= 1"),
            (set(self.map_lr) <= set(MAP_NAMES), f"map_lr keys must be among {MAP_NAMES}"),
            (all(v >= 0 for v in self.map_lr.values()), "map_lr factors must be >= 0"),
            (set(self.prior_maps) <= set(MAP_NAMES), f"prior_maps must be among {MAP_NAMES}"),
            (set(self.project_lr) <= set(MAP_KINDS), f"project_lr must be among {MAP_KINDS}"),
            (set(self.check_prior) <= set(MAP_KINDS), f"check_prior must be among {MAP_KINDS}"),
            (0.0 <= self.detail_gain <= 1.0, "detail_gain must be within 0 and 1"),
            (
                self.max_prior_scale is None or self.max_prior_scale >= 2,
                "max_prior_scale must be None or >= 2",
            ),
            (
                self.blend_margin >= 0 and self.blend_network_db >= 0,
                "blend_margin and blend_network_db must be >= 0",
            ),
            (
                self.blend_pick_db is None or self.blend_pick_db >= 0,
                "blend_pick_db must be None or >= 0",
            ),
            (
                self.blend_channel_db is None or self.blend_channel_db >= 0,
                "blend_channel_db must be None or >= 0",
            ),
            (self.self_ensemble in (1, 2, 4, 8), "self_ensemble must be 1, 2, 4 or 8"),
            (
                set(self.self_ensemble_by_kind) <= set(MAP_KINDS)
                and all(v in (1, 2, 4, 8) for v in self.self_ensemble_by_kind.values()),
                f"self_ensemble_by_kind maps kinds among {MAP_KINDS} to 1, 2, 4 or 8",
            ),
            (
                self.self_ensemble_max_scale is None or self.self_ensemble_max_scale >= 2,
                "self_ensemble_max_scale must be None or >= 2",
            ),
            (
                self.normal_pick_max_scale is None or self.normal_pick_max_scale >= 2,
                "normal_pick_max_scale must be None or >= 2",
            ),
            (self.reach_db is None or self.reach_db > 0, "reach_db must be None or > 0"),
            (
                self.pseudo_gt_self_ensemble in (1, 2, 4, 8),
                "pseudo_gt_self_ensemble must be 1, 2, 4 or 8",
            ),
        ]
        for ok, msg in checks:
            if not ok:
                raise InvalidOptions(f"PBR-SR config '{self.name}': {msg}")
        if self.pseudo_gt_prior is not None:
            from ..prior.registry import check_name

            check_name(self.pseudo_gt_prior)

    @property
    def weight_map_lr(self) -> float:
        return self.lr if self.lr_weight_maps is None else self.lr_weight_maps

    def copies(self, scale: int) -> tuple[int, dict[str, int]]:
        """(``self_ensemble``, ``self_ensemble_by_kind``) for maps upscaled by ``scale``."""
        if self.self_ensemble_max_scale is not None and scale > self.self_ensemble_max_scale:
            return 1, {}
        return self.self_ensemble, self.self_ensemble_by_kind

    def to_dict(self) -> dict:
        return asdict(self)

    def with_(self, **changes) -> PbrsrConfig:
        """A copy with some numbers changed (e.g. ``with_(iterations=50)``)."""
        return replace(self, **changes)


PAPER = PbrsrConfig(
    name="paper",
    view_mode="orbit",  # 15 x 50 = 750 views at distance 3.25, FoV 10 (paper)
    n_elev=15,
    n_azim=50,
    distance=3.25,
    fov_deg=10.0,
    render_res=1024,  # pseudo-GT 1024x1024 (paper; its ablation: higher is better)
    iterations=2000,
    batch_views=4,
    lr=1e-4,  # Adam, constant
    sampling="views",
    mask_unseen=False,  # the paper optimises every texel
    eval_views=240,
)

# CPU presets. Why each shared number is what it is (x4, LR by `pbrsr degrade`, render PSNR
# over evaluation views under two HDRs; docs/METHOD.md has the same measurements in context):
# * fov 30 at distance 3.25 frames the whole unit-size mesh (bounding-sphere radius <= 0.87 <
#   3.25 tan 15 deg), so a few views cover it; the paper's FoV 10 sees only the central part.
# * render_res None: resolution from texel density, one pixel per HR texel, capped by
#   max_render_res (the cost of a step is proportional to the pixels shaded).
# * target "detail" and several views per texel: on the 512 demo asset (24 evaluation views,
#   60 iterations) the paper's target (the prior's output) lost 3.5 dB of albedo PSNR against
#   bicubic and gained 0.1 dB render PSNR; "detail" with 3 views per texel kept every map at or
#   above bicubic (albedo +0.3, roughness +0.5, occlusion +2.5 dB) and gained 0.6 dB render
#   PSNR. Adam steps of 5e-3 move every texel by its full step each iteration: speckle.
# * lr 2.5e-4 and lambda_pix 1 (the paper: 1e-4 and 100). With the prior's output
#   back-projected onto its input (prior/backproject.py) the init alone scores best, and the
#   pixel loss against the pseudo-GT pulls the maps away from it. balanced, 60 evaluation
#   views, render PSNR init / 25 steps at lr 1e-3 / at 2.5e-4: Avocado 41.61 / 41.41 / 41.56
#   (albedo 46.34 / 44.47 / 45.69, bicubic 45.81), ToyCar 34.58 / 34.37 / 34.56, cabinet
#   30.61 / 30.45 / 30.51. lambda_pix 0 keeps the Avocado at 41.59 (albedo 46.07); lambda_pbr 0
#   drops it to 39.94: the consistency term holds the maps, the pseudo-GT moves them. lambda_pix
#   1 against 10: +0.0..+0.08 dB render PSNR on the Avocado, ToyCar and cabinet (Avocado albedo
#   46.10 against 45.69 dB). The paper's 100 stays in `paper`, for strong priors on a farm.
# * iterations: render PSNR peaks within 10-25 steps and then the maps overfit the pseudo-GT
#   (balanced, prior on the albedo only, 0 / 10 / 25 / 50 / 60 steps: ToyCar 34.00 / 34.09 /
#   34.04 / 33.88 / 33.77; cabinet at 0 / 10 / 25 / 40 / 60: 30.39 / 30.48 / 30.47 / 30.44 /
#   30.39); `--iterations 25` is within that peak.
# * map_lr normal 0.3: the render loss moves the normal maps more than their pseudo-GT
#   supports. balanced (120 evaluation views, rrdn-thick), normal lr x1 / x0.3: render PSNR
#   cabinet 28.98 / 29.08, tea set 31.75 / 31.75, table 31.30 / 31.29, ToyCar 33.55 / 33.62;
#   cabinet normal 35.53 / 35.78 (bicubic 35.82). Metallic x0.3 lost 0.2-0.5 dB of metallic
#   PSNR on the tea set and ToyCar, so metallic keeps the full rate.
# * map_lr emissive 0: emission adds light, so the render loss can explain any brightness
#   residual with it. balanced (120 evaluation views), emissive ToyCar / WaterBottle: bicubic
#   41.87 / 50.99 dB; the prior's init 41.65 / 51.09; optimised from the prior's init 41.60 /
#   50.72, from bicubic 41.83 / 48.52; render PSNR within 0.05 dB across all of these. A map
#   whose every rate is 0 is rendered as a fixed texture, never differentiated.
# * prior_maps: every map, each map (each channel of an ORM image) self-checked. With the
#   back-projected prior the direct prior beats a fast preset whose metallic and emissive
#   maps come from bicubic by 1.6 dB render PSNR on the BoomBox (metallic 23.05 against 20.13,
#   emissive 48.70 against 41.43) and by 1.6 dB on the procedural asset (metallic 30.50
#   against 27.65), 120 evaluation views.
# * project_lr colour and data: the optimiser's maps drift from the LR model (the render loss
#   and TV move low frequencies too); one back-projection step onto the (deblocked) LR maps
#   puts that back and keeps what the optimiser added above the LR grid. balanced, 60
#   evaluation views, render PSNR direct / without the step / with it: ToyCar 34.29 / 34.19 /
#   34.55 (roughness 37.21 / 38.23 dB, metallic 31.79 / 32.22 without / with), BoomBox 25.17 /
#   25.06 / 25.32, Avocado and cabinet within 0.01 dB. Normal maps are not projected: the
#   cabinet's scores 37.03 dB projected against 37.17, its render 0.13 dB less (its LR normals
#   are renormalised after the blur, which the LR model does not invert).
PRIOR_MAPS_CPU = MAP_NAMES
PROJECT_LR_CPU = ("colour", "data")
# * check_prior colour and data, not normal maps. Unchecked, the prior would cost the Avocado's
#   roughness 0.67 dB (-0.04 one scale down) and the BoomBox's constant occlusion channel 72 dB
#   (-47 one scale down). Normal maps checked too (`check_prior=colour|data|normal`, pbr-srmd's
#   normal network and waifu2x-photo as candidates, bicubic the fallback; `pbrsr bench upscale`,
#   the seven shared assets, 40 evaluation views): at x4 the ToyCar's normal map goes to
#   waifu2x-photo's (direct 29.51 -> 29.61 dB, render +0.02) and no other map moves (a WebXR
#   trigger's, docs/BENCHMARKS.md, from 26.96 to 27.78, above bicubic's 27.62); at x2 the ToyCar's
#   goes to bicubic, whose one-scale-down score ties the networks' (27.26 dB, waifu2x-photo
#   27.24, the network 27.16) where at the real scale they gain +2.6 to +3.3 dB, and the
#   WaterBottle's, flat one scale down, where the network gains +0.6: direct's mean render
#   gain over bicubic +2.46 against +2.63, balanced +2.50 against +2.69.
CHECK_PRIOR_CPU = ("colour", "data")
# * normal_pick_max_scale 4: at x2 and x4 a normal map takes whichever of the prior's normal
#   candidates (pbr-srmd: its normal network, waifu2x-photo) reconstructs it best one scale
#   down, never bicubic and with no flat rule (the check above without them). Published x4
#   runs against the normal network on every normal map (40 evaluation views): on the twelve
#   WebXR controllers the generic trigger's knurled normal map goes to waifu2x-photo (26.93 ->
#   27.77 dB in direct, bicubic 27.62; render +0.09 in direct, fast and balanced), every other
#   render the same to the hundredth; on the seven shared assets the ToyCar's (29.51 -> 29.61,
#   render +0.02), means +2.31 / +2.50 / +2.41 dB over bicubic for direct / fast / balanced;
#   at x2 the ToyCar's (39.43 -> 40.20 dB in direct, render +0.04; balanced +0.01). At x8,
#   where a normal map is three x2 passes, the pick hands waifu2x-photo maps that render
#   further (cabinet -0.45 dB, mean -0.11): the normal network (docs/METHOD.md, "Colour and
#   data maps checked, normal maps picked"). The pick costs 0.08-0.91 s a map on balanced's
#   two copies, a sixth to a ninth of the map's own upscale on large maps, 3-4 % of a run.
NORMAL_PICK_MAX_SCALE_CPU = 4
# * reach_db: None in every preset. At 25 dB (`+reach_db=25` in `pbrsr bench upscale`, x4, the
#   seven shared assets, 40 evaluation views) the renders move by -0.01..0.00 dB per asset and
#   balanced runs 5 % faster on average (ToyCar 23.8 -> 19.2 s, cabinet 10.4 -> 8.6, the rest
#   within noise; the measurement itself 0.6-1.4 s), and no map scores below bicubic; but the
#   ToyCar's roughness goes to bicubic's (46.33 -> 37.12 dB): the renders of this renderer,
#   under these lights, do not show it, and a scene that lights it otherwise, or shades a
#   clearcoat over it, would (docs/METHOD.md, "Maps the renders do not show").
# * blend_data: each data channel a least-squares blend, fitted one scale down, of the prior's
#   candidates, bicubic and (roughness, metallic) the colour-guided upscale (prior/blend.py).
#   x4, 40 evaluation views, mean render gain over bicubic without / with: balanced +1.96 /
#   +2.08 dB, fast +1.79 / +1.89 (BoomBox +0.41, WaterBottle +0.28, ToyCar +0.16 with
#   balanced; pbr-upconv7); run times the same or shorter (docs/BENCHMARKS.md, "Data
#   channels blended"). blend_network_db 0.1 dB, blend_margin 0, blend_pick_db None (`pbrsr
#   bench blend`, held-out materials' packed maps, x4, pbr-srmd; gain over bicubic, networks
#   per map): +0.958 dB with 0.62 networks (margin 0.1 +0.896: one fabric's roughness kept
#   bicubic's; every network +1.003 with 1.08; the pick alone +0.987 with 1.15), JPEG 95
#   +0.274, JPEG 85 +0.105 (margin 0.1: +0.226, +0.094). The margin decides no map of the
#   shared assets with pbr-srmd or pbr-upconv7. blend_pick_db 0 (the pick kept unless the
#   blend fits better) gains +0.995 / +0.323 / +0.139 there, nearly all of it the same fabric,
#   and costs the BoomBox's render 0.22 dB (fast) and 0.48 (balanced) on the shared assets,
#   its roughness (fast, -1.28 dB) or metallic (balanced, -1.16 dB) given to the check's pick
#   where the blend was closer at the real scale (docs/METHOD.md, "Data channels blended").
#   blend_pick_floor (a network kept where leaving it out puts a channel's blend below the
#   pick one scale down) gains +0.997 dB there with 0.81 networks per map (pbr-upconv7 +1.034
#   against +1.026), nearly all of it the fabric, and on the shared assets moves the BoomBox's
#   render only: +0.67 dB with pbr-upconv7, -0.15 with pbr-srmd (balanced; fast +0.17 and
#   -0.18): off (docs/METHOD.md, "Where the network rule loses").
# * blend_channel_db 0.1 in fast, balanced and quality: a network kept on a map is left out of
#   each channel it adds less than 0.1 dB to, one scale down. The held-out materials' blends
#   (`pbrsr bench blend --margins 0 --network-db 0.1 --channel-db off,0.05,0.1,0.2`, x4,
#   pbr-srmd) gain +0.950 dB over bicubic with 0.92 network runs per map, against +0.958 with
#   1.08. The published x4 run (`fast` against `fast+blend_channel_db=null`, the seven shared
#   assets, 40 evaluation views) moves the WaterBottle's render +0.03 dB in 0.91x its time and
#   the ToyCar's -0.01, mean +2.42 dB either way; at x2 it leaves the table's metallic 0.07 dB
#   below bicubic (0.02 without), a map the renders do not show (docs/METHOD.md, "A network
#   per channel").
# * detail_gain 0.5 in fast, balanced and quality (direct takes balanced's): a colour or data
#   map's departure from bicubic scaled by half its gain fitted one scale down. The published x4
#   run (the seven shared assets, 40 evaluation views) against the same table without it:
#   direct +2.28 -> +2.30 dB over bicubic, fast +2.42 -> +2.49 (BoomBox +0.37), balanced +2.41
#   either way, direct with waifu2x-photo +1.91 -> +1.98. The full gain on every map kind lost
#   0.025 dB in direct's renders, on normal maps alone 0.059 (docs/METHOD.md, "The network's
#   detail scaled by a gain fitted one scale down").
# * self_ensemble_by_kind {"normal": 2} in balanced: normal maps on two copies of the prior, the
#   other kinds on one. Published runs, the seven shared assets, 40 evaluation views, balanced
#   against `balanced+blend_channel_db=null+self_ensemble_by_kind={}`: x4 +2.41 against +2.36
#   dB over bicubic (15.6 against 15.2 s), x2 +2.66 against +2.62 (1.12x); the normal maps gain
#   most from copies on the held-out materials too (docs/BENCHMARKS.md, "Normal maps on two
#   copies of the prior"). fast keeps one copy: +2.42 -> +2.46 dB in 1.19x, a larger share of
#   its shorter run. quality takes eight of every kind at every scale (x8: +1.21 against
#   balanced's +1.14 dB in 6.5x its time, docs/BENCHMARKS.md "x8").
# * self_ensemble_max_scale 4 in balanced: at x8 a normal map is three x2 passes and a copy
#   runs all three; the published x8 run against `balanced+self_ensemble_max_scale=null`:
#   +1.144 against +1.146 dB over bicubic in 0.86x the time (32.4 against 37.5 s), the
#   renders -0.03..+0.07 dB per asset (docs/BENCHMARKS.md, "x8").
# * fast: PBR-SR's init and export with no optimisation steps, the prior at x2 of the scale
#   (max_prior_scale 2; bicubic the rest, then the back-projection step). waifu2x-photo's x2
#   pass on a 512² map costs 2.1 s against 13.0 s for its x4 (two passes), and on the shared
#   assets' maps (whole maps, x4 by the protocol's LR) keeps most of the x4's gain over
#   bicubic: albedo Avocado +1.47 of +1.75 dB, ToyCar +3.31 of +4.73, WaterBottle +1.84 of
#   +2.22, BoomBox +4.00 of +4.67; data maps +0.76 of +0.60 (Avocado) .. +2.54 of +3.06
#   (ToyCar); normal maps +0.39 of +0.40 (Avocado) .. +1.99 of +2.25 (BoomBox). 5 Adam steps of
#   2.5e-4 move no texel by more than 1.25e-3 (a third of an 8-bit level) and moved render
#   PSNR by -0.01..+0.02 dB in every fast run of `pbrsr bench upscale` (120 views), while the
#   steps, with the view selection, G-buffers and pseudo-GT they need, cost 20-30 % of fast's
#   time (WaterBottle 25.2 against 20.7 s, Avocado 18.3 against 14.5 s). Its view and step
#   numbers below are the ones those steps were measured with, and apply to
#   ``FAST.with_(iterations=...)``. bfloat16 for the prior (2.1x faster on an AVX512-BF16 CPU)
#   is not used: it cost the Avocado's roughness 0.67 dB of the prior's gain (x4, whole map).
# * balanced: the init and export of fast with the prior at the full scale, no optimisation
#   steps. The steps move render PSNR by hundredths of a dB: `pbrsr bench upscale --methods
#   balanced+iterations=0` against the same preset with its 25 steps over up to 16 views
#   (pbr-upconv7, 40 evaluation views): procedural 27.44 / 27.44, Avocado 41.92 / 41.90,
#   BoomBox 25.48 / 25.51, ToyCar 34.69 / 34.72, while the steps with their views, G-buffers
#   and pseudo-GT took 41-67 % of the run (Avocado 44 of 106 s, BoomBox 71 of 157 s, ToyCar
#   56 of 83 s). What balanced gains over fast (ToyCar +0.21, WaterBottle +0.32 dB) is the
#   prior at the full scale, not the steps.
# * quality: balanced with the prior averaged over the eight symmetries of each map
#   (self_ensemble 8: +0.06..+0.34 dB render over balanced on every shared asset, +0.13 on
#   average, in 6.0x its time; two copies +0.08 in 1.7x; docs/BENCHMARKS.md, "The prior
#   averaged over the square's symmetries"), no optimisation steps. 25 steps over its views
#   (``iterations`` 25: up to 16 views, renders up to 512²) move the render by -0.06..+0.02 dB
#   per shared asset on that init, -0.02 on average, and by the same to the hundredth with
#   the pseudo-GT's renders averaged over eight copies as well (pseudo_gt_self_ensemble 8);
#   on one copy's init +0.01 (docs/BENCHMARKS.md, "quality, fast with copies of the prior,
#   and optimiser steps"); 40 steps over 32 views at 768² gained -0.01..+0.01 dB more in
#   1.7-2.2x the time (Avocado, BoomBox, ToyCar). Its view numbers are the ones those steps
#   were measured with. fast with eight copies leads it in the mean (+2.54 against +2.49 dB)
#   through one JPEG map (the tea set's metallic) and trails it on the PNG data maps.

_CPU = PbrsrConfig(
    view_mode="coverage",
    fov_deg=30.0,
    render_res=None,
    target="detail",
    check_prior=CHECK_PRIOR_CPU,
    normal_pick_max_scale=NORMAL_PICK_MAX_SCALE_CPU,
    blend_data=True,
    deblock_jpeg=True,
    lr=2.5e-4,
    prior_maps=PRIOR_MAPS_CPU,
    map_lr={"normal": 0.3, "emissive": 0.0},
    blend_channel_db=0.1,
    detail_gain=0.5,
    project_lr=PROJECT_LR_CPU,
    lambda_pix=1.0,
    mask_unseen=True,
)
"""What the CPU presets share (see the comments above); each names only what differs."""

FAST = _CPU.with_(
    name="fast",
    max_prior_scale=2,
    iterations=0,
    n_candidates=48,  # candidate views rasterised at low resolution for selection
    max_views=6,  # few views: pseudo-GT costs one prior call per view
    max_render_res=384,
    views_per_texel=2,
    batch_views=2,
    log_every=5,
)

BALANCED = FAST.with_(
    name="balanced",
    max_prior_scale=None,
    self_ensemble_by_kind={"normal": 2},
    self_ensemble_max_scale=4,
)

QUALITY = BALANCED.with_(
    name="quality",
    self_ensemble=8,
    self_ensemble_by_kind={},
    self_ensemble_max_scale=None,
    # the views its steps were measured with (``iterations``; none by default)
    n_candidates=64,
    max_views=16,
    max_render_res=512,  # 512: one pixel per texel on a 512 map seen face-on
    views_per_texel=3,
    log_every=10,
)

PRESETS: dict[str, PbrsrConfig] = {p.name: p for p in (FAST, BALANCED, QUALITY, PAPER)}


def run_config(preset: str, iterations: int | None = None) -> PbrsrConfig:
    """The config of a run: the preset called ``preset`` with ``iterations`` optimiser steps
    when given (a run's ``UpscaleOptions.iterations``)."""
    config = get_preset(preset)
    return config if iterations is None else config.with_(iterations=iterations)


def get_preset(name: str) -> PbrsrConfig:
    """The preset called ``name`` (fast, balanced, quality, paper)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise InvalidOptions(
            f"unknown preset {name!r}: choose one of {', '.join(PRESETS)}"
        ) from None
