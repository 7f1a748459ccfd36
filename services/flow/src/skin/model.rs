//! The adaptive skin-colour term of section 3: per camera, a skin and a background colour
//! distribution in RGB, bootstrapped from Jones and Rehg's generic Gaussian mixtures
//! ("Statistical color models with application to skin detection", IJCV 46(1), 2002;
//! 16 diagonal kernels per class, the published parameters) and adapted from face
//! detections: colours of the faces' central regions join the skin model, the rest of the
//! image the background model. Equation 4: `h = sum_q min(log10(Ps(u)/Pbg(u)), alpha)`.

use crate::skin::faces::FaceBox;

/// Bins per channel of the colour histograms (32^3 bins of 8 grey levels).
pub const BINS: usize = 32;
const SHIFT: u32 = 3;

/// One kernel: mean (R, G, B), variance (R, G, B), weight.
type Kernel = ([f32; 3], [f32; 3], f32);

/// Jones & Rehg's skin mixture.
pub const JONES_REHG_SKIN: [Kernel; 16] = [
    ([73.53, 29.94, 17.76], [765.40, 121.44, 112.80], 0.0294),
    ([249.71, 233.94, 217.49], [39.94, 154.44, 396.05], 0.0331),
    ([161.68, 116.25, 96.95], [291.03, 60.48, 162.85], 0.0654),
    ([186.07, 136.62, 114.40], [274.95, 64.60, 198.27], 0.0756),
    ([189.26, 98.37, 51.18], [633.18, 222.40, 250.69], 0.0554),
    ([247.00, 152.20, 90.84], [65.23, 691.53, 609.92], 0.0314),
    ([150.10, 72.66, 37.76], [408.63, 200.77, 257.57], 0.0454),
    ([206.85, 171.09, 156.34], [530.08, 155.08, 572.79], 0.0469),
    ([212.78, 152.82, 120.04], [160.57, 84.52, 243.90], 0.0956),
    ([234.87, 175.43, 138.94], [163.80, 121.57, 279.22], 0.0763),
    ([151.19, 97.74, 74.59], [425.40, 73.56, 175.11], 0.1100),
    ([120.52, 77.55, 59.82], [330.45, 70.34, 151.82], 0.0676),
    ([192.20, 119.62, 82.32], [152.76, 92.14, 259.15], 0.0755),
    ([214.29, 136.08, 87.24], [204.90, 140.17, 270.19], 0.0500),
    ([99.57, 54.33, 38.06], [448.13, 90.18, 151.29], 0.0667),
    ([238.88, 203.08, 176.91], [178.38, 156.27, 404.99], 0.0749),
];

/// Jones & Rehg's non-skin mixture.
pub const JONES_REHG_NON_SKIN: [Kernel; 16] = [
    ([254.37, 254.41, 253.82], [2.77, 2.81, 5.46], 0.0637),
    ([9.39, 8.09, 8.52], [46.84, 33.59, 32.48], 0.0516),
    ([96.57, 96.95, 91.53], [280.69, 156.79, 436.58], 0.0864),
    ([160.44, 162.49, 159.06], [355.98, 115.89, 591.24], 0.0636),
    ([74.98, 63.23, 46.33], [414.84, 245.95, 361.27], 0.0747),
    ([121.83, 60.88, 18.31], [2502.24, 1383.53, 237.18], 0.0365),
    ([202.18, 154.88, 91.04], [957.42, 1766.94, 1582.52], 0.0349),
    ([193.06, 201.93, 206.55], [562.88, 190.23, 447.28], 0.0649),
    ([51.88, 57.14, 61.55], [344.11, 191.77, 433.40], 0.0656),
    ([30.88, 26.84, 25.32], [222.07, 118.65, 182.41], 0.1189),
    ([44.97, 85.96, 131.95], [651.32, 840.52, 963.67], 0.0362),
    ([236.02, 236.27, 230.70], [225.03, 117.29, 331.95], 0.0849),
    ([207.86, 191.20, 164.12], [494.04, 237.69, 533.52], 0.0368),
    ([99.83, 148.11, 188.17], [955.88, 654.95, 916.70], 0.0389),
    ([135.06, 131.92, 123.10], [350.35, 130.30, 388.43], 0.0943),
    ([135.96, 103.89, 66.88], [806.44, 642.20, 350.36], 0.0477),
];

/// Density of a diagonal Gaussian mixture at an RGB colour.
pub fn mixture_density(kernels: &[Kernel], rgb: [f32; 3]) -> f32 {
    kernels
        .iter()
        .map(|(mean, var, weight)| {
            let e: f32 = (0..3).map(|k| (rgb[k] - mean[k]).powi(2) / var[k]).sum();
            weight * (-0.5 * e).exp() / ((2.0 * std::f32::consts::PI).powf(1.5) * (var[0] * var[1] * var[2]).sqrt())
        })
        .sum()
}

/// Histogram bin of a colour.
#[inline(always)]
pub fn bin(rgb: [u8; 3]) -> usize {
    ((rgb[0] as usize >> SHIFT) * BINS + (rgb[1] as usize >> SHIFT)) * BINS + (rgb[2] as usize >> SHIFT)
}

/// A normalised colour histogram (sums to one).
#[derive(Clone, Debug, PartialEq)]
pub struct ColourHistogram {
    p: Vec<f32>,
}

impl ColourHistogram {
    /// A mixture evaluated at bin centres and normalised.
    pub fn from_mixture(kernels: &[Kernel]) -> Self {
        let w = (1u32 << SHIFT) as f32;
        let mut p = vec![0f32; BINS * BINS * BINS];
        for r in 0..BINS {
            for g in 0..BINS {
                for b in 0..BINS {
                    let centre = [(r as f32 + 0.5) * w, (g as f32 + 0.5) * w, (b as f32 + 0.5) * w];
                    p[(r * BINS + g) * BINS + b] = mixture_density(kernels, centre);
                }
            }
        }
        let mut h = Self { p };
        h.normalise();
        h
    }

    fn normalise(&mut self) {
        let total: f32 = self.p.iter().sum();
        if total > 0.0 {
            self.p.iter_mut().for_each(|v| *v /= total);
        }
    }

    /// Probability of a colour's bin.
    pub fn probability(&self, rgb: [u8; 3]) -> f32 {
        self.p[bin(rgb)]
    }
}

/// A camera's skin model: skin and background distributions and the clamped log ratio.
#[derive(Clone, Debug)]
pub struct SkinModel {
    skin: ColourHistogram,
    background: ColourHistogram,
    generic_skin: ColourHistogram,
    generic_background: ColourHistogram,
    alpha: f32,
    adaptation_rate: f32,
    /// `min(log10(Ps / Pbg), alpha)` per bin, refreshed after every adaptation.
    log_ratio: Vec<f32>,
    adaptations: u32,
}

/// Share of the generic prior that adaptation never replaces.
pub const GENERIC_SHARE: f32 = 0.25;

/// Brightness factors applied to each face colour when adapting the skin model.
const SHADING_SCALES: [f32; 4] = [0.7, 0.85, 1.0, 1.1];

/// Probability floor (per bin) so that unseen colours have a finite log ratio.
const FLOOR: f32 = 1e-7;

impl SkinModel {
    /// The generic model (Jones & Rehg), before any adaptation. `alpha` starts at 1 (a
    /// skin colour ten times likelier under the skin model counts fully), as the note on
    /// skin priors measured on a real face; adaptation re-estimates it.
    pub fn generic(adaptation_rate: f32) -> Self {
        let generic_skin = ColourHistogram::from_mixture(&JONES_REHG_SKIN);
        let generic_background = ColourHistogram::from_mixture(&JONES_REHG_NON_SKIN);
        let mut model = Self {
            skin: generic_skin.clone(),
            background: generic_background.clone(),
            generic_skin,
            generic_background,
            alpha: 1.0,
            adaptation_rate: adaptation_rate.clamp(0.0, 1.0),
            log_ratio: Vec::new(),
            adaptations: 0,
        };
        model.refresh();
        model
    }

    /// The clamp of equation 4.
    pub fn alpha(&self) -> f32 {
        self.alpha
    }

    /// Face detections used so far.
    pub fn adaptations(&self) -> u32 {
        self.adaptations
    }

    /// `min(log10(Ps/Pbg), alpha)` of a colour.
    #[inline(always)]
    pub fn log_ratio(&self, rgb: [u8; 3]) -> f32 {
        self.log_ratio[bin(rgb)]
    }

    /// The skin decision: the skin model is the likelier.
    pub fn is_skin(&self, rgb: [u8; 3]) -> bool {
        self.log_ratio(rgb) > 0.0
    }

    /// The log ratio of the distributions used: the adapted ones with a fixed share of the
    /// generic prior kept, so colours a face never shows (a hand in shadow, seen from the
    /// side) keep the prior's opinion instead of decaying to nothing.
    fn unclamped(&self, b: usize) -> f32 {
        let g = GENERIC_SHARE;
        let skin = (1.0 - g) * self.skin.p[b] + g * self.generic_skin.p[b];
        let background = (1.0 - g) * self.background.p[b] + g * self.generic_background.p[b];
        ((skin + FLOOR) / (background + FLOOR)).log10()
    }

    fn refresh(&mut self) {
        let alpha = self.alpha;
        self.log_ratio = (0..BINS * BINS * BINS).map(|b| self.unclamped(b).min(alpha)).collect();
    }

    /// Adapts to one camera image (RGB8) given the faces detected in it: central-face
    /// colours blend into the skin distribution, all pixels outside the faces into the
    /// background one (the paper's rule),
    /// each with weight `adaptation_rate`. Alpha becomes the median unclamped log ratio of
    /// the central-face pixels: half of a face's skin saturates the term, so one very
    /// skin-like colour cannot outweigh several views (equation 4 sums over views). Returns
    /// false, changing nothing, when there is no face: the model keeps its last state.
    pub fn adapt(&mut self, rgb: &[u8], width: u32, height: u32, faces: &[FaceBox]) -> bool {
        let (w, h) = (width as usize, height as usize);
        if faces.is_empty() || w == 0 || rgb.len() != w * h * 3 {
            return false;
        }
        let mut skin = vec![0f32; BINS * BINS * BINS];
        // Counted in integers (exact; the f32 sums they replace were exact below 2^24 too).
        let mut background_counts = vec![0u32; BINS * BINS * BINS];
        let mut skin_bins = Vec::new();
        for (y, row) in rgb.chunks_exact(w * 3).enumerate() {
            let v = y as f32 + 0.5;
            // A row no face box spans is background throughout: counted without testing
            // every pixel against the faces (that test was most of a face round's time
            // beside the detector itself).
            let spanned = faces.iter().any(|f| {
                let (_, y0, _, fh) = f.skin_region();
                (v >= f.y && v <= f.y + f.height) || (v >= y0 && v <= y0 + fh)
            });
            if !spanned {
                for px in row.chunks_exact(3) {
                    background_counts[bin([px[0], px[1], px[2]])] += 1;
                }
                continue;
            }
            for (x, px) in row.chunks_exact(3).enumerate() {
                let colour = [px[0], px[1], px[2]];
                let b = bin(colour);
                let u = x as f32 + 0.5;
                let central = faces.iter().any(|f| {
                    let (x0, y0, fw, fh) = f.skin_region();
                    u >= x0 && v >= y0 && u <= x0 + fw && v <= y0 + fh
                });
                if central {
                    // The same skin under less or more light: shading scales all channels
                    // alike, so hands and the sides of the head, lit differently from the
                    // face's centre, still match.
                    for k in SHADING_SCALES {
                        let shaded = colour.map(|c| (f32::from(c) * k).min(255.0) as u8);
                        skin[bin(shaded)] += 1.0;
                    }
                    skin_bins.push(b);
                } else if !faces.iter().any(|f| f.contains(u, v)) {
                    // The rest of the face box (hair, eyes, background corners) goes nowhere.
                    background_counts[b] += 1;
                }
            }
        }
        let background: Vec<f32> = background_counts.iter().map(|&c| c as f32).collect();
        if skin_bins.is_empty() {
            return false;
        }
        blend(&mut self.skin.p, &skin, self.adaptation_rate);
        blend(&mut self.background.p, &background, self.adaptation_rate);
        let mut ratios: Vec<f32> = skin_bins.iter().map(|&b| self.unclamped(b)).collect();
        let mid = ratios.len() / 2;
        ratios.select_nth_unstable_by(mid, f32::total_cmp);
        self.alpha = ratios[mid].max(0.1);
        self.adaptations += 1;
        self.refresh();
        true
    }
}

/// `p <- (1 - rate) p + rate * counts / sum(counts)`.
fn blend(p: &mut [f32], counts: &[f32], rate: f32) {
    let total: f32 = counts.iter().sum();
    if total <= 0.0 {
        return;
    }
    for (pi, c) in p.iter_mut().zip(counts) {
        *pi = (1.0 - rate) * *pi + rate * c / total;
    }
}

/// Skin shares (the stream's log, the second reference's trust) are counted on every
/// this-many-th pixel: a share to a percent is enough, not an exact count, and it must cost
/// the stream nothing. 61 pixels of `f32` are about four cache lines, so a frame's maps are
/// read a quarter; every 7th pixel touched every line, 0.8 % of a replay's CPU time. A
/// 1280x720 view still gives 15,000 samples (a prime stride does not follow the image's
/// columns).
pub const SKIN_SHARE_STRIDE: usize = 61;

/// Share of a skin map's pixels (clamped log10 skin ratios) above `threshold`, counting every
/// `stride`-th one (see [`SKIN_SHARE_STRIDE`]); 0 for an empty map.
pub fn skin_share_of(map: &[f32], threshold: f32, stride: usize) -> f32 {
    let (mut skin, mut seen) = (0usize, 0usize);
    for &r in map.iter().step_by(stride.max(1)) {
        seen += 1;
        skin += usize::from(r > threshold);
    }
    skin as f32 / seen.max(1) as f32
}

/// Equation 4 for one scene point: the sum over views of the clamped log ratio of the colour
/// each view sees there.
pub fn skin_term(models: &[SkinModel], colours: &[[u8; 3]]) -> f32 {
    models.iter().zip(colours).map(|(m, &c)| m.log_ratio(c)).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_skin_share_counts_the_sampled_pixels_above_the_threshold() {
        let map: Vec<f32> = (0..100).map(|i| if i % 2 == 0 { 0.5 } else { -0.5 }).collect();
        assert_eq!(skin_share_of(&map, 0.0, 1), 0.5);
        assert_eq!(skin_share_of(&map, 0.0, 2), 1.0, "every other pixel: the skin ones only");
        assert_eq!(skin_share_of(&map, 0.5, 1), 0.0, "at the threshold is not above it");
        assert_eq!(skin_share_of(&[], 0.0, 61), 0.0);
    }

    #[test]
    fn the_generic_prior_separates_typical_skin_from_typical_background() {
        let m = SkinModel::generic(0.3);
        assert!(m.is_skin([224, 172, 140]), "light skin");
        assert!(m.is_skin([150, 95, 70]), "darker skin");
        assert!(!m.is_skin([40, 60, 110]), "blue cloth");
        assert!(!m.is_skin([250, 250, 250]), "white wall");
        assert!(!m.is_skin([10, 10, 10]), "black");
        assert!(m.log_ratio([224, 172, 140]) <= m.alpha());
    }

    #[test]
    fn mixture_densities_integrate_to_about_one() {
        // Riemann sum over the bin centres (8^3 volume per bin).
        let h: f32 = (0..BINS * BINS * BINS)
            .map(|b| {
                let (r, g, bl) = (b / (BINS * BINS), (b / BINS) % BINS, b % BINS);
                let c = [(r as f32 + 0.5) * 8.0, (g as f32 + 0.5) * 8.0, (bl as f32 + 0.5) * 8.0];
                mixture_density(&JONES_REHG_SKIN, c) * 512.0
            })
            .sum();
        assert!((h - 1.0).abs() < 0.05, "{h}");
    }

    #[test]
    fn adaptation_learns_an_unusual_skin_tone_from_a_face() {
        // A greenish "skin" the generic model rejects, on a reddish background it accepts.
        let (w, h) = (40u32, 40u32);
        let mut rgb = vec![0u8; (w * h * 3) as usize];
        for y in 0..h {
            for x in 0..w {
                let i = ((y * w + x) * 3) as usize;
                let face = (10..30).contains(&x) && (10..30).contains(&y);
                let c = if face { [120, 160, 90] } else { [200, 120, 90] };
                rgb[i..i + 3].copy_from_slice(&c);
            }
        }
        let face = FaceBox { x: 10.0, y: 10.0, width: 20.0, height: 20.0, score: 5.0 };
        let mut m = SkinModel::generic(0.5);
        assert!(!m.is_skin([120, 160, 90]));
        assert!(m.adapt(&rgb, w, h, &[face]));
        assert!(m.is_skin([120, 160, 90]), "learnt from the face");
        assert!(!m.is_skin([200, 120, 90]), "learnt as background");
        assert!(m.alpha() > 0.1);
        // No face: nothing changes.
        let before = m.log_ratio([120, 160, 90]);
        assert!(!m.adapt(&rgb, w, h, &[]));
        assert_eq!(m.log_ratio([120, 160, 90]), before);
        assert_eq!(m.adaptations(), 1);
    }

    #[test]
    fn the_skin_term_sums_clamped_views() {
        let m = SkinModel::generic(0.3);
        let one = m.log_ratio([224, 172, 140]);
        let h = skin_term(&[m.clone(), m.clone(), m], &[[224, 172, 140]; 3]);
        assert!((h - 3.0 * one).abs() < 1e-5);
    }
}
