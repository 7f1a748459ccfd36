//! Normalised colour images: the engine's own pixel storage.
//!
//! Pixels are four `f32` (R, G, B, and a zero pad) so that one bilinear tap is one aligned
//! 16-byte load the compiler can vectorise. Images are normalised per camera (section 2.2 of
//! the paper): every channel loses its own mean, and all channels share one scale so that the
//! image has unit variance. That removes per-camera gain, offset and colour cast while keeping
//! colour.

/// One pixel: R, G, B and an unused pad lane (always zero).
pub type Rgba = [f32; 4];

/// A normalised colour image, row-major.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColourImage {
    width: usize,
    height: usize,
    pixels: Vec<Rgba>,
}

impl ColourImage {
    /// A black image; the buffer is reused by [`ColourImage::resize`] and the normalisers.
    pub fn new(width: usize, height: usize) -> Self {
        Self { width, height, pixels: vec![[0.0; 4]; width * height] }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// All pixels, row-major.
    pub fn pixels(&self) -> &[Rgba] {
        &self.pixels
    }

    /// All pixels, row-major, writable.
    pub fn pixels_mut(&mut self) -> &mut [Rgba] {
        &mut self.pixels
    }

    /// Reshapes the image, reallocating only when it grows.
    pub fn resize(&mut self, width: usize, height: usize) {
        self.width = width;
        self.height = height;
        self.pixels.resize(width * height, [0.0; 4]);
    }

    /// The pixel at integer coordinates (no bounds forgiveness: callers clamp).
    #[inline(always)]
    pub fn at(&self, x: usize, y: usize) -> Rgba {
        self.pixels[y * self.width + x]
    }

    /// Fills `self` from interleaved RGB8 and normalises it to zero mean per channel and unit
    /// variance over all channels. A flat image (no variance) is left at zero mean, unscaled.
    pub fn set_normalised_from_rgb8(&mut self, width: usize, height: usize, rgb: &[u8]) {
        use rayon::prelude::*;
        debug_assert_eq!(rgb.len(), width * height * 3);
        self.resize(width, height);
        let table = normalisation_table(width, height, rgb);
        let row_bytes = (width * 3).max(1);
        self.pixels
            .par_chunks_mut(width.max(1))
            .zip(rgb.par_chunks(row_bytes))
            .for_each(|(dst, row)| normalised_row(dst, row, &table));
    }

    /// What [`ColourImage::set_normalised_from_rgb8`] followed by
    /// [`ColourImage::downsample_into`] gives, the same values, without writing and reading
    /// back the full-resolution float image (a third of the memory traffic of building a
    /// frame's pyramid when nothing matches at full resolution).
    pub fn set_normalised_half_from_rgb8(&mut self, width: usize, height: usize, rgb: &[u8], rings: &mut PieceRings) {
        debug_assert_eq!(rgb.len(), width * height * 3);
        if width == 0 || height == 0 {
            self.resize(0, 0);
            return;
        }
        let table = normalisation_table(width, height, rgb);
        halve_streamed(width.div_ceil(2), height, self, rings, |y, out| {
            normalised_half_row(out, &rgb[y * width * 3..][..width * 3], width, &table)
        });
    }

    /// Bilinear sample at subpixel `(x, y)` (pixel centres at integers), or `None` when the
    /// point lies outside the image: a view that does not see a point must not vote on it.
    #[inline(always)]
    pub fn sample(&self, x: f32, y: f32) -> Option<Rgba> {
        let max_x = (self.width - 1) as f32;
        let max_y = (self.height - 1) as f32;
        if !(x >= 0.0 && y >= 0.0 && x <= max_x && y <= max_y) {
            return None;
        }
        if self.width < 2 || self.height < 2 {
            return Some(self.bilinear_at(x as usize, y as usize, 0.0, 0.0));
        }
        // x, y >= 0: truncation is floor. The last column/row interpolates from its left/upper
        // neighbour with weight 1, so the 2x2 block always lies inside.
        let ix = (x as usize).min(self.width - 2);
        let iy = (y as usize).min(self.height - 2);
        let (fx, fy) = (x - ix as f32, y - iy as f32);
        let top_start = iy * self.width + ix;
        let bottom_start = top_start + self.width;
        let (a, b) = (self.pixels[top_start], self.pixels[top_start + 1]);
        let (c, d) = (self.pixels[bottom_start], self.pixels[bottom_start + 1]);
        // Four weights broadcast over the four lanes: one SIMD multiply-add chain.
        let (w00, w01) = ((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy));
        let (w10, w11) = ((1.0 - fx) * fy, fx * fy);
        Some([
            a[0] * w00 + b[0] * w01 + c[0] * w10 + d[0] * w11,
            a[1] * w00 + b[1] * w01 + c[1] * w10 + d[1] * w11,
            a[2] * w00 + b[2] * w01 + c[2] * w10 + d[2] * w11,
            a[3] * w00 + b[3] * w01 + c[3] * w10 + d[3] * w11,
        ])
    }

    /// Bilinear interpolation inside the 2x2 block whose top-left texel is `(ix, iy)`.
    /// The caller guarantees `ix + 1 < width` and `iy + 1 < height` (or a 1-pixel axis).
    #[inline(always)]
    pub fn bilinear_at(&self, ix: usize, iy: usize, fx: f32, fy: f32) -> Rgba {
        let w = self.width;
        let x1 = (ix + 1).min(w - 1);
        let y1 = (iy + 1).min(self.height - 1);
        let a = self.pixels[iy * w + ix];
        let b = self.pixels[iy * w + x1];
        let c = self.pixels[y1 * w + ix];
        let d = self.pixels[y1 * w + x1];
        std::array::from_fn(|k| {
            let top = a[k] + (b[k] - a[k]) * fx;
            let bottom = c[k] + (d[k] - c[k]) * fx;
            top + (bottom - top) * fy
        })
    }

    /// Writes into `dst` this image halved: a separable [1 3 3 1]/8 filter centred between
    /// each pair of pixels, so that pixel `i` of the coarse image sits at `2i + 0.5` of this
    /// one (the convention [`crate::matching::camera::LevelProjection`] uses) and aliasing is
    /// damped.
    pub fn downsample_into(&self, dst: &mut ColourImage, rings: &mut PieceRings) {
        let w = self.width;
        halve_streamed(w.div_ceil(2).max(1), self.height, dst, rings, |y, out| {
            half_row(out, &self.pixels[y * w..][..w])
        });
    }
}

/// Most parallel pieces a streamed pass cuts an image into ([`piece_rows`]).
const PIECES: usize = 4;

/// Output rows of one parallel piece of a streamed pass ([`halve_streamed`],
/// [`ColourImage::local_normalise_into`]): a quarter of the image, so two threads share an
/// image's pieces evenly while each piece recomputes few of the input rows it shares with
/// the piece before. At most [`PIECES`] pieces.
fn piece_rows(height: usize) -> usize {
    height.div_ceil(PIECES).max(16)
}

/// The rows each parallel piece of a streamed pass keeps, reused from frame to frame (a
/// steady stream allocates nothing per frame).
#[derive(Clone, Debug, Default)]
pub struct PieceRings {
    pieces: Vec<PieceRing>,
}

/// One piece's ring: `slots` rows of texels, the image row each slot holds, and the slots
/// the current output row reads.
#[derive(Clone, Debug, Default)]
struct PieceRing {
    texels: Vec<Rgba>,
    held: Vec<usize>,
    reads: Vec<usize>,
}

impl PieceRings {
    /// One ring per piece of an output `height` rows tall, each of `slots` rows `width`
    /// texels wide, holding no row yet; with the pieces' length in output rows.
    fn for_pass(&mut self, height: usize, width: usize, slots: usize) -> (&mut [PieceRing], usize) {
        let piece = piece_rows(height);
        let count = height.div_ceil(piece).max(1);
        if self.pieces.len() < count {
            self.pieces.resize_with(count, PieceRing::default);
        }
        for ring in &mut self.pieces[..count] {
            if ring.texels.len() < slots * width {
                ring.texels.resize(slots * width, [0.0; 4]);
            }
            ring.held.clear();
            ring.held.resize(slots, usize::MAX);
            ring.reads.clear();
            ring.reads.resize(slots, 0);
        }
        (&mut self.pieces[..count], piece)
    }
}

impl PieceRing {
    /// The offset in `texels` of image row `source`, `width` texels wide, written by `fill`
    /// unless its slot still holds it. Any run of consecutive rows no longer than the ring
    /// falls in different slots.
    fn row(&mut self, source: usize, width: usize, fill: impl FnOnce(&mut [Rgba])) -> usize {
        let slot = source % self.held.len();
        if self.held[slot] != source {
            fill(&mut self.texels[slot * width..][..width]);
            self.held[slot] = source;
        }
        slot * width
    }
}

/// The vertical pass of halving, streamed: `dst` becomes `cw` x `ceil(height / 2)`, its
/// row `cy` the [`HALF_TAPS`] filter of rows `2cy - 1 ..= 2cy + 2` (clamped) of the
/// horizontally halved image, whose row `y` `half_row_of(y, out)` writes. Each piece of
/// output rows keeps the four halved rows it reads in a ring that stays in cache, instead
/// of a halved image written whole and read back (on four 1280x720 views, 30 MB per frame
/// set through memory); the values are the same, bit for bit.
fn halve_streamed(
    cw: usize,
    height: usize,
    dst: &mut ColourImage,
    rings: &mut PieceRings,
    half_row_of: impl Fn(usize, &mut [Rgba]) + Sync,
) {
    use rayon::prelude::*;
    dst.resize(cw, height.div_ceil(2).max(1));
    let (rings, piece) = rings.for_pass(dst.height, cw, 4);
    dst.pixels.par_chunks_mut(cw * piece).zip(rings.par_iter_mut()).enumerate().for_each(|(p, (out_piece, ring))| {
        for (i, out) in out_piece.chunks_mut(cw).enumerate() {
            let cy = p * piece + i;
            let rows: [usize; 4] = std::array::from_fn(|t| {
                let y = clamp_index(2 * cy as isize - 1 + t as isize, height);
                ring.row(y, cw, |row| half_row_of(y, row))
            });
            vertical_half_row(out, &ring.texels, rows);
        }
    });
}

/// Taps of the [1 3 3 1]/8 filter that halves an image.
const HALF_TAPS: [f32; 4] = [0.125, 0.375, 0.375, 0.125];

#[inline(always)]
fn clamp_index(v: isize, n: usize) -> usize {
    v.clamp(0, n as isize - 1) as usize
}

/// [`HALF_TAPS`] applied to four consecutive texels, summed in tap order (every halving pass
/// goes through here, so they agree to the bit).
#[inline(always)]
fn half_filter(texels: [Rgba; 4]) -> Rgba {
    let mut acc = [0.0f32; 4];
    for (p, weight) in texels.iter().zip(HALF_TAPS) {
        for k in 0..4 {
            acc[k] += weight * p[k];
        }
    }
    acc
}

/// The horizontal pass of halving: `out[cx]` filters texels `2cx - 1 ..= 2cx + 2` of a row
/// `width` wide (clamped at its ends), each given by `texel`.
#[inline(always)]
fn horizontal_half(out: &mut [Rgba], width: usize, texel: impl Fn(usize) -> Rgba) {
    for (cx, o) in out.iter_mut().enumerate() {
        *o = half_filter(std::array::from_fn(|t| texel(clamp_index(2 * cx as isize - 1 + t as isize, width))));
    }
}

crate::matching::isa::vectorised_fn! {
    /// One row of normalised texels from interleaved RGB8.
    fn normalised_row(out: &mut [Rgba], rgb: &[u8], table: &[[f32; 256]; 3]) {
        for (d, px) in out.iter_mut().zip(rgb.chunks_exact(3)) {
            *d = normalised_texel(table, px);
        }
    }
}

crate::matching::isa::vectorised_fn! {
    /// The horizontal pass of halving one RGB8 row `width` pixels wide, normalised on the way:
    /// what [`horizontal_half`] computes, bit for bit, but each input pixel is looked up once.
    /// Output `cx` reads pixels `2cx - 1 ..= 2cx + 2`; the last two are the next output's
    /// first two, so they are carried over instead of looked up again (the table lookups
    /// were most of this pass).
    fn normalised_half_row(out: &mut [Rgba], rgb: &[u8], width: usize, table: &[[f32; 256]; 3]) {
        let texel = |x: isize| {
            let x = clamp_index(x, width);
            normalised_texel(table, &rgb[3 * x..3 * x + 3])
        };
        let mut carried = [texel(-1), texel(0)];
        for (cx, o) in out.iter_mut().enumerate() {
            let next = [texel(2 * cx as isize + 1), texel(2 * cx as isize + 2)];
            *o = half_filter([carried[0], carried[1], next[0], next[1]]);
            carried = next;
        }
    }
}

crate::matching::isa::vectorised_fn! {
    /// The horizontal pass of halving one row of texels.
    fn half_row(out: &mut [Rgba], row: &[Rgba]) {
        horizontal_half(out, row.len(), |x| row[x]);
    }
}

crate::matching::isa::vectorised_fn! {
    /// One output row of the vertical pass: texels of the four rows of `halved` starting at
    /// the offsets `rows`, filtered.
    fn vertical_half_row(out: &mut [Rgba], halved: &[Rgba], rows: [usize; 4]) {
        for (cx, o) in out.iter_mut().enumerate() {
            *o = half_filter(rows.map(|row| halved[row + cx]));
        }
    }
}

/// Per channel, the normalised value of each of the 256 levels: zero mean per channel and
/// unit variance over all channels of the whole image (a flat image is left at zero mean,
/// unscaled). One table lookup per pixel instead of a subtraction and a product.
fn normalisation_table(width: usize, height: usize, rgb: &[u8]) -> [[f32; 256]; 3] {
    use rayon::prelude::*;
    let n = (width * height).max(1) as f64;
    // Exact integer sums, rows in parallel.
    let row_bytes = (width * 3).max(1);
    // Pieces of at most 65,536 whole pixels: a lane of `channel_sums` then adds at most
    // 4,096 squares of 255.
    let piece = row_bytes.min(3 * 65_536);
    let (sum, sum_sq) = rgb.par_chunks(row_bytes).flat_map_iter(|row| row.chunks(piece)).map(channel_sums).reduce(
        || ([0u64; 3], [0u64; 3]),
        |(a, b), (c, d)| (std::array::from_fn(|k| a[k] + c[k]), std::array::from_fn(|k| b[k] + d[k])),
    );
    let mean = sum.map(|s| s as f64 / n);
    let variance: f64 = (0..3).map(|c| sum_sq[c] as f64 / n - mean[c] * mean[c]).sum::<f64>() / 3.0;
    let scale = if variance > 1e-9 { 1.0 / variance.sqrt() } else { 1.0 };
    std::array::from_fn(|c| std::array::from_fn(|v| ((v as f64 - mean[c]) * scale) as f32))
}

/// Bytes summed lane by lane in [`channel_sums`]: sixteen pixels, so lane `i` always holds
/// channel `i % 3`.
const SUM_LANES: usize = 48;

crate::matching::isa::vectorised_fn! {
    /// Per channel, the sum and the sum of squares of one RGB8 row. Sixteen pixels at a time
    /// into 48 `u32` lanes (they vectorise; a pixel's three bytes do not), folded into the
    /// channels at the end: exact while a lane adds fewer than 66,000 squares of 255, rows
    /// of about a million pixels (the caller splits longer ones).
    fn channel_sums(row: &[u8]) -> ([u64; 3], [u64; 3]) {
        let (mut lane_sum, mut lane_sq) = ([0u32; SUM_LANES], [0u32; SUM_LANES]);
        let blocks = row.chunks_exact(SUM_LANES);
        let tail = blocks.remainder();
        for block in blocks {
            for i in 0..SUM_LANES {
                let v = u32::from(block[i]);
                lane_sum[i] += v;
                lane_sq[i] += v * v;
            }
        }
        let (mut s, mut q) = ([0u64; 3], [0u64; 3]);
        for i in 0..SUM_LANES {
            s[i % 3] += u64::from(lane_sum[i]);
            q[i % 3] += u64::from(lane_sq[i]);
        }
        // The tail starts on a pixel boundary: 48 is a multiple of 3.
        for (i, &b) in tail.iter().enumerate() {
            let v = u64::from(b);
            s[i % 3] += v;
            q[i % 3] += v * v;
        }
        (s, q)
    }
}

#[inline(always)]
fn normalised_texel(table: &[[f32; 256]; 3], px: &[u8]) -> Rgba {
    [table[0][usize::from(px[0])], table[1][usize::from(px[1])], table[2][usize::from(px[2])], 0.0]
}

/// A coarse-to-fine stack: level 0 is full resolution, each further level half the size.
///
/// Besides the normalised colour levels, a pyramid can hold *matching* levels: each level
/// locally contrast-normalised (see [`ColourImage::local_normalise_into`]), which makes weak
/// texture as discriminative as strong texture.
#[derive(Clone, Debug, Default)]
pub struct Pyramid {
    levels: Vec<ColourImage>,
    matching: Vec<ColourImage>,
    rings: PieceRings,
}

/// Parameters of local contrast normalisation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalNormalisation {
    /// Half-size of the square neighbourhood, pixels.
    pub radius: usize,
    /// Standard deviation added in quadrature to the local one (normalised units), so flat
    /// regions are not amplified into noise.
    pub floor: f32,
}

impl Pyramid {
    /// Rebuilds the pyramid from RGB8 in place (buffers are reused across frames), with
    /// matching levels when `local` is given, from level `matching_from` up (finer matching
    /// levels are left empty: an engine estimating only coarser levels never reads them; for
    /// the same reason a `matching_from` of 1 or more leaves colour level 0 empty too).
    pub fn rebuild(
        &mut self,
        width: usize,
        height: usize,
        rgb: &[u8],
        levels: usize,
        local: Option<LocalNormalisation>,
        matching_from: usize,
    ) {
        let levels = levels.max(1);
        self.levels.resize_with(levels, ColourImage::default);
        // Nothing reads a level finer than the first matched one: when that is level 1 or
        // coarser, level 0 is left empty and level 1 is built straight from the bytes.
        let first = if matching_from >= 1 && levels >= 2 {
            self.levels[0].resize(0, 0);
            self.levels[1].set_normalised_half_from_rgb8(width, height, rgb, &mut self.rings);
            2
        } else {
            self.levels[0].set_normalised_from_rgb8(width, height, rgb);
            1
        };
        for l in first..levels {
            let (finer, coarser) = self.levels.split_at_mut(l);
            finer[l - 1].downsample_into(&mut coarser[0], &mut self.rings);
        }
        match local {
            Some(params) => {
                self.matching.resize_with(levels, ColourImage::default);
                for (l, (src, dst)) in self.levels.iter().zip(self.matching.iter_mut()).enumerate() {
                    if l >= matching_from {
                        src.local_normalise_into(dst, params, &mut self.rings);
                    }
                }
            }
            None => self.matching.clear(),
        }
    }

    /// Level `l` (0 = full resolution).
    pub fn level(&self, l: usize) -> &ColourImage {
        &self.levels[l]
    }

    /// The image to match on at level `l`: the locally normalised one when built, else the
    /// normalised colour level.
    pub fn matching_level(&self, l: usize) -> &ColourImage {
        self.matching.get(l).unwrap_or(&self.levels[l])
    }

    /// Number of levels.
    pub fn len(&self) -> usize {
        self.levels.len()
    }

    /// True when nothing has been built yet.
    pub fn is_empty(&self) -> bool {
        self.levels.is_empty()
    }
}

impl ColourImage {
    /// Writes into `dst` this image with every pixel's neighbourhood mean removed (per
    /// channel) and divided by the neighbourhood's standard deviation (over all channels,
    /// plus `floor` in quadrature): the per-pixel form of normalised cross-correlation.
    pub fn local_normalise_into(&self, dst: &mut ColourImage, params: LocalNormalisation, rings: &mut PieceRings) {
        use rayon::prelude::*;
        let (w, h) = (self.width, self.height);
        dst.resize(w, h);
        if w == 0 || h == 0 {
            return;
        }
        let r = params.radius as isize;
        let side = 2 * params.radius + 1;
        let area = (side * side) as f32;
        let floor_sq = params.floor * params.floor;
        // Pieces of rows in parallel, each keeping the horizontal box sums of the `side` rows
        // its current row needs in a ring that stays in cache (the whole image's sums were
        // written and read back seven times); the values are the same, bit for bit.
        let (rings, piece) = rings.for_pass(h, w, side);
        dst.pixels.par_chunks_mut(w * piece).zip(rings.par_iter_mut()).enumerate().for_each(
            |(p, (out_piece, ring))| {
                for (i, out) in out_piece.chunks_mut(w).enumerate() {
                    let y = p * piece + i;
                    for (k, dy) in (-r..=r).enumerate() {
                        let source = clamp_index(y as isize + dy, h);
                        ring.reads[k] = ring.row(source, w, |row| box_sum_row(row, &self.pixels[source * w..][..w], r));
                    }
                    normalised_box_row(out, &self.pixels[y * w..][..w], &ring.texels, &ring.reads, area, floor_sq);
                }
            },
        );
    }
}

crate::matching::isa::vectorised_fn! {
    /// Horizontal box sums of radius `r` along one row, of every channel and (pad lane) of
    /// the sum of squares over channels; the row's ends are clamped.
    fn box_sum_row(out: &mut [Rgba], row: &[Rgba], r: isize) {
        let w = row.len();
        let clamp = |v: isize| v.clamp(0, w as isize - 1) as usize;
        let mut acc = [0.0f32; 4];
        for dx in -r..=r {
            add_with_square(&mut acc, row[clamp(dx)], 1.0);
        }
        for (x, o) in out.iter_mut().enumerate() {
            *o = acc;
            add_with_square(&mut acc, row[clamp(x as isize - r)], -1.0);
            add_with_square(&mut acc, row[clamp(x as isize + r + 1)], 1.0);
        }
    }
}

crate::matching::isa::vectorised_fn! {
    /// One row of local normalisation: the horizontal box sums of the rows about it
    /// (those of `sums` starting at the offsets `rows`, in order) summed into `out`, then
    /// `src` normalised by the box's mean and deviation.
    fn normalised_box_row(out: &mut [Rgba], src: &[Rgba], sums: &[Rgba], rows: &[usize], area: f32, floor_sq: f32) {
        let w = src.len();
        out.iter_mut().for_each(|o| *o = [0.0; 4]);
        for &start in rows {
            for (o, s) in out.iter_mut().zip(&sums[start..start + w]) {
                for k in 0..4 {
                    o[k] += s[k];
                }
            }
        }
        for (o, p) in out.iter_mut().zip(src) {
            let mean = [o[0] / area, o[1] / area, o[2] / area];
            let mean_sq = o[3] / (3.0 * area);
            let var = (mean_sq - (mean[0] * mean[0] + mean[1] * mean[1] + mean[2] * mean[2]) / 3.0).max(0.0);
            let inv = 1.0 / (var + floor_sq).sqrt();
            *o = [(p[0] - mean[0]) * inv, (p[1] - mean[1]) * inv, (p[2] - mean[2]) * inv, 0.0];
        }
    }
}

#[inline(always)]
fn add_with_square(acc: &mut [f32; 4], p: Rgba, sign: f32) {
    acc[0] += sign * p[0];
    acc[1] += sign * p[1];
    acc[2] += sign * p[2];
    acc[3] += sign * (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(width: usize, height: usize) -> ColourImage {
        let mut img = ColourImage::new(width, height);
        for y in 0..height {
            for x in 0..width {
                img.pixels_mut()[y * width + x] = [x as f32, y as f32, (x + 2 * y) as f32, 0.0];
            }
        }
        img
    }

    #[test]
    fn bilinear_sampling_is_exact_on_a_linear_ramp() {
        let img = ramp(7, 5);
        let s = img.sample(2.25, 3.5).expect("inside");
        assert!((s[0] - 2.25).abs() < 1e-6);
        assert!((s[1] - 3.5).abs() < 1e-6);
        assert!((s[2] - 9.25).abs() < 1e-5);
        // The far border itself is inside.
        let s = img.sample(6.0, 4.0).expect("border is inside");
        assert_eq!(s[0], 6.0);
        assert_eq!(s[1], 4.0);
    }

    #[test]
    fn samples_outside_the_image_are_refused() {
        let img = ramp(4, 4);
        assert!(img.sample(-0.01, 1.0).is_none());
        assert!(img.sample(1.0, 3.01).is_none());
        assert!(img.sample(f32::NAN, 1.0).is_none());
    }

    #[test]
    fn normalisation_gives_zero_mean_unit_variance_whatever_the_gain() {
        let (w, h) = (16, 8);
        let base: Vec<u8> = (0..w * h * 3).map(|i| ((i * 37) % 200) as u8).collect();
        let gained: Vec<u8> = base.iter().map(|&v| v / 2 + 20).collect();
        let mut a = ColourImage::default();
        let mut b = ColourImage::default();
        a.set_normalised_from_rgb8(w, h, &base);
        b.set_normalised_from_rgb8(w, h, &gained);
        let n = (w * h) as f32;
        for c in 0..3 {
            let mean: f32 = a.pixels().iter().map(|p| p[c]).sum::<f32>() / n;
            assert!(mean.abs() < 1e-4, "channel {c} mean {mean}");
        }
        let var: f32 = a.pixels().iter().map(|p| p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sum::<f32>() / (3.0 * n);
        assert!((var - 1.0).abs() < 1e-3);
        // Gain and offset vanish up to the rounding of v/2.
        let diff: f32 = a.pixels().iter().zip(b.pixels()).map(|(p, q)| (p[0] - q[0]).abs()).sum::<f32>() / n;
        assert!(diff < 0.03, "mean abs difference {diff}");
    }

    #[test]
    fn channel_sums_are_exact_at_every_row_length() {
        let mut state = 12345u32;
        let mut byte = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 24) as u8
        };
        for pixels in [0usize, 1, 15, 16, 17, 47, 640, 1283] {
            let row: Vec<u8> = (0..3 * pixels).map(|_| byte()).collect();
            let (mut s, mut q) = ([0u64; 3], [0u64; 3]);
            for (i, &b) in row.iter().enumerate() {
                s[i % 3] += u64::from(b);
                q[i % 3] += u64::from(b) * u64::from(b);
            }
            assert_eq!(channel_sums(&row), (s, q), "{pixels} pixels");
        }
        let white = vec![255u8; 3 * 65_536];
        let n = 65_536u64;
        assert_eq!(channel_sums(&white), ([255 * n; 3], [255 * 255 * n; 3]), "the longest piece, all 255");
    }

    #[test]
    fn local_normalisation_equalises_contrast() {
        // The same pattern at two contrasts becomes the same after local normalisation.
        let (w, h) = (20, 10);
        let mut img = ColourImage::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let pattern = if (x + y) % 2 == 0 { 1.0 } else { -1.0 };
                let gain = if x < w / 2 { 0.1 } else { 2.0 };
                img.pixels_mut()[y * w + x] = [gain * pattern + 5.0, gain * pattern, -gain * pattern, 0.0];
            }
        }
        let mut out = ColourImage::default();
        img.local_normalise_into(&mut out, LocalNormalisation { radius: 1, floor: 1e-3 }, &mut PieceRings::default());
        let left = out.at(3, 5);
        let right = out.at(15, 5);
        for k in 0..3 {
            assert!((left[k] - right[k]).abs() < 0.05, "channel {k}: {} vs {}", left[k], right[k]);
        }
        // Mean removed: the +5 offset of the red channel is gone.
        assert!(left[0].abs() < 2.0);
    }

    #[test]
    fn the_half_resolution_build_equals_normalising_then_halving() {
        // Odd and even sizes, so both clamped borders are exercised.
        for (w, h) in [(7, 5), (8, 6), (1, 1), (2, 3)] {
            let rgb: Vec<u8> = (0..w * h * 3).map(|i| ((i * 37 + i / 5 * 11) % 256) as u8).collect();
            let mut full = ColourImage::default();
            full.set_normalised_from_rgb8(w, h, &rgb);
            let (mut halved, mut direct) = (ColourImage::default(), ColourImage::default());
            let mut rings = PieceRings::default();
            full.downsample_into(&mut halved, &mut rings);
            direct.set_normalised_half_from_rgb8(w, h, &rgb, &mut rings);
            assert_eq!((direct.width(), direct.height()), (halved.width(), halved.height()), "{w}x{h}");
            assert_eq!(direct.pixels(), halved.pixels(), "{w}x{h}: the same values, bit for bit");
        }
    }

    /// A deterministic image with texture at every scale.
    fn textured(w: usize, h: usize) -> ColourImage {
        let mut img = ColourImage::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let v = ((x * 7 + y * 13) % 17) as f32 + ((x * y) % 5) as f32 * 0.3;
                img.pixels_mut()[y * w + x] = [v, 0.5 * v - (y % 3) as f32, (x % 4) as f32, 0.0];
            }
        }
        img
    }

    #[test]
    fn images_of_many_pieces_halve_as_the_filter_says_at_every_row() {
        // Tall enough for several parallel pieces, odd so the last row is clamped.
        let (w, h) = (9, 141);
        let img = textured(w, h);
        let mut half = ColourImage::default();
        img.downsample_into(&mut half, &mut PieceRings::default());
        assert_eq!((half.width(), half.height()), (5, 71));
        let at = |x: isize, y: isize| img.at(clamp_index(x, w), clamp_index(y, h));
        for cy in 0..71isize {
            for cx in 0..5isize {
                let mut expected = [0.0f32; 4];
                for (j, wy) in HALF_TAPS.iter().enumerate() {
                    for (i, wx) in HALF_TAPS.iter().enumerate() {
                        let p = at(2 * cx - 1 + i as isize, 2 * cy - 1 + j as isize);
                        for k in 0..4 {
                            expected[k] += wx * wy * p[k];
                        }
                    }
                }
                let got = half.at(cx as usize, cy as usize);
                for k in 0..4 {
                    assert!(
                        (got[k] - expected[k]).abs() < 1e-4,
                        "({cx}, {cy}) channel {k}: {} vs {}",
                        got[k],
                        expected[k]
                    );
                }
            }
        }
    }

    #[test]
    fn images_of_many_pieces_are_locally_normalised_as_defined_at_every_row() {
        let (w, h) = (11, 137);
        let img = textured(w, h);
        let params = LocalNormalisation { radius: 3, floor: 0.05 };
        let mut out = ColourImage::default();
        img.local_normalise_into(&mut out, params, &mut PieceRings::default());
        let r = params.radius as isize;
        let area = ((2 * r + 1) * (2 * r + 1)) as f64;
        for y in 0..h {
            for x in 0..w {
                // The box's mean per channel and deviation over channels, rows and columns
                // clamped at the borders.
                let (mut sum, mut sum_sq) = ([0.0f64; 3], 0.0f64);
                for dy in -r..=r {
                    for dx in -r..=r {
                        let p = img.at(clamp_index(x as isize + dx, w), clamp_index(y as isize + dy, h));
                        for k in 0..3 {
                            sum[k] += f64::from(p[k]);
                            sum_sq += f64::from(p[k]) * f64::from(p[k]);
                        }
                    }
                }
                let mean = sum.map(|s| s / area);
                let var = (sum_sq / (3.0 * area) - mean.iter().map(|m| m * m).sum::<f64>() / 3.0).max(0.0);
                let inv = 1.0 / (var + f64::from(params.floor).powi(2)).sqrt();
                let (p, got) = (img.at(x, y), out.at(x, y));
                for k in 0..3 {
                    let expected = (f64::from(p[k]) - mean[k]) * inv;
                    assert!(
                        (f64::from(got[k]) - expected).abs() < 1e-3,
                        "({x}, {y}) channel {k}: {} vs {expected}",
                        got[k]
                    );
                }
            }
        }
    }

    #[test]
    fn pyramid_levels_halve_and_keep_the_pixel_centre_convention() {
        // A ramp in x stays a ramp: coarse pixel i sits at fine coordinate 2i + 0.5.
        let (w, h) = (32, 16);
        let mut rgb = vec![0u8; w * h * 3];
        for y in 0..h {
            for x in 0..w {
                rgb[(y * w + x) * 3] = (x * 4) as u8;
                rgb[(y * w + x) * 3 + 1] = (y * 8) as u8;
            }
        }
        let mut pyr = Pyramid::default();
        pyr.rebuild(w, h, &rgb, 3, None, 0);
        assert_eq!(pyr.len(), 3);
        assert_eq!((pyr.level(1).width(), pyr.level(1).height()), (16, 8));
        assert_eq!((pyr.level(2).width(), pyr.level(2).height()), (8, 4));
        let fine = pyr.level(0);
        let coarse = pyr.level(1);
        for cx in 1..15 {
            let expected = fine.sample(2.0 * cx as f32 + 0.5, 6.5).expect("inside")[0];
            let got = coarse.at(cx, 3)[0];
            assert!((expected - got).abs() < 1e-4, "x {cx}: {expected} vs {got}");
        }
    }
}
