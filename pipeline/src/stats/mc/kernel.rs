//! The per-pair kernel: draw the two spin axes, project them, add intrinsic polarization,
//! ISM and noise, apply the cut, fold Delta gamma.
use super::super::rng::Xoshiro256pp;
use super::{McConfig, PIntDist};

/// Precomputed per-run constants of the kernel.
pub(super) struct Kernel<'a> {
    cfg: &'a McConfig,
    model_constant: f64,
    /// Mean foreground (q, u) added to both components, percent.
    ism_qu: (f64, f64),
    /// Scatter of the foreground about `ism_qu`: the lower-triangular Cholesky factor
    /// (l_qq, l_uq, l_uu) of its covariance, percent; None: a fixed foreground.
    ism_chol: Option<[f64; 3]>,
    /// Noise sigma of q and u of component A and B, percent.
    noise: [f64; 2],
    /// (K sigma)^2 of each component, percent^2.
    cut2: Option<[f64; 2]>,
}

const RAD_TO_DEG: f64 = 180.0 / std::f64::consts::PI;

impl<'a> Kernel<'a> {
    pub(super) fn new(cfg: &'a McConfig) -> Self {
        let ism_qu = cfg.ism.map_or((0.0, 0.0), |ism| {
            let (s, c) = (2.0 * ism.angle_deg.to_radians()).sin_cos();
            (ism.p_percent * c, ism.p_percent * s)
        });
        let noise = cfg.noise_percent.unwrap_or(0.0);
        Self::with(cfg, ism_qu, None, [noise; 2])
    }

    /// The kernel of one binary: its own foreground (mean (q, u) and, if given, the Cholesky
    /// factor of its covariance, percent) and its own noise of A and B (percent), with the
    /// cut of `cfg`.
    pub(super) fn with(cfg: &'a McConfig, ism_qu: (f64, f64), ism_chol: Option<[f64; 3]>, noise: [f64; 2]) -> Self {
        let cut2 = cfg.snr_cut.map(|k| noise.map(|s| (k * s) * (k * s)));
        Self {
            cfg,
            model_constant: cfg.model.sampler_constant(),
            ism_qu,
            ism_chol,
            noise,
            cut2,
        }
    }

    /// True when the polarization (not only the geometry) has to be simulated.
    fn simulates_polarization(&self) -> bool {
        self.cfg.simulates_polarization() || self.ism_chol.is_some() || self.noise != [0.0; 2]
    }

    /// Intrinsic (q, u) of a disk with projected axis (x, y), percent.
    #[inline]
    fn intrinsic(&self, rng: &mut Xoshiro256pp, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        if let PIntDist::Sin2i { p_max_percent } = self.cfg.p_int {
            // P_max sin^2 i (cos 2g, sin 2g) = -P_max (x^2 - y^2, 2xy): no division.
            return (-p_max_percent * (x * x - y * y), -p_max_percent * 2.0 * x * y);
        }
        intrinsic_qu(self.cfg.p_int.draw(rng, r2), x, y)
    }

    /// Simulate `n` pairs of chunk `chunk`, calling `sink` with each accepted Delta gamma
    /// (degrees); returns the number accepted.
    #[inline]
    pub(super) fn run_chunk(&self, chunk: u64, n: u64, sink: &mut impl FnMut(f64)) -> u64 {
        let mut rng = Xoshiro256pp::for_stream(self.cfg.seed, chunk);
        let model = &self.cfg.model;
        let pol = self.simulates_polarization();
        let mut accepted = 0;
        for _ in 0..n {
            let n1 = rng.unit_vector();
            let (x1, y1) = (n1[0], n1[1]);
            let (x2, y2) = model.second_axis(&mut rng, n1, self.model_constant);
            let flip1 = perpendicular(&mut rng, self.cfg.perpendicular_fraction[0]);
            let flip2 = perpendicular(&mut rng, self.cfg.perpendicular_fraction[1]);
            if !pol {
                let dg = delta_gamma_axes(x1, y1, x2, y2);
                // One polarization rotated by 90 deg: the folded difference becomes 90 - dg.
                sink(if flip1 != flip2 { 90.0 - dg } else { dg });
                accepted += 1;
                continue;
            }
            let (mut q1, mut u1) = self.intrinsic(&mut rng, x1, y1);
            let (mut q2, mut u2) = self.intrinsic(&mut rng, x2, y2);
            // A 90-deg rotation of the polarization angle is (q, u) -> (-q, -u).
            if flip1 {
                (q1, u1) = (-q1, -u1);
            }
            if flip2 {
                (q2, u2) = (-q2, -u2);
            }
            let (mut iq, mut iu) = self.ism_qu;
            if let Some([lqq, luq, luu]) = self.ism_chol {
                // One foreground per pair, common to both components: mean + L z.
                let (a, b) = rng.normal_pair();
                iq += lqq * a;
                iu += luq * a + luu * b;
            }
            q1 += iq;
            u1 += iu;
            q2 += iq;
            u2 += iu;
            let [s1, s2] = self.noise;
            if s1 > 0.0 || s2 > 0.0 {
                let (a, b) = rng.normal_pair();
                let (c, d) = rng.normal_pair();
                q1 += s1 * a;
                u1 += s1 * b;
                q2 += s2 * c;
                u2 += s2 * d;
            }
            if let Some([c1, c2]) = self.cut2 {
                if !(q1 * q1 + u1 * u1 > c1 && q2 * q2 + u2 * u2 > c2) {
                    continue;
                }
            }
            sink(delta_gamma_qu(q1, u1, q2, u2));
            accepted += 1;
        }
        accepted
    }
}

/// Whether a disk is polarized perpendicular to its projected long axis (probability `f`);
/// draws a uniform only for 0 < f < 1, so f = 0 leaves every seeded result unchanged.
#[inline]
fn perpendicular(rng: &mut Xoshiro256pp, f: f64) -> bool {
    if f <= 0.0 {
        false
    } else if f >= 1.0 {
        true
    } else {
        rng.uniform() < f
    }
}

/// Folded angle between two projected axes (x, y) taken as lines, degrees in [0, 90].
#[inline]
pub(crate) fn delta_gamma_axes(x1: f64, y1: f64, x2: f64, y2: f64) -> f64 {
    let cross = x1 * y2 - y1 * x2;
    let dot = x1 * x2 + y1 * y2;
    cross.abs().atan2(dot.abs()) * RAD_TO_DEG
}

/// Folded difference of the polarization angles of two (q, u), degrees in [0, 90]:
/// 2 Delta gamma is the angle between the (q, u) vectors.
#[inline]
pub(crate) fn delta_gamma_qu(q1: f64, u1: f64, q2: f64, u2: f64) -> f64 {
    let cross = q1 * u2 - u1 * q2;
    let dot = q1 * q2 + u1 * u2;
    0.5 * cross.abs().atan2(dot) * RAD_TO_DEG
}

/// (q, u) of degree `p` polarized along the long axis of a disk whose projected spin axis
/// is (x, y): gamma = PA(axis) + 90 deg, so (cos 2g, sin 2g) = -(x^2 - y^2, 2xy) / r^2.
#[inline]
pub(crate) fn intrinsic_qu(p: f64, x: f64, y: f64) -> (f64, f64) {
    let r2 = x * x + y * y;
    if r2 > 0.0 {
        let f = -p / r2;
        (f * (x * x - y * y), f * 2.0 * x * y)
    } else {
        (p, 0.0) // exactly face-on: the angle is undefined; any choice has measure zero
    }
}
