//! Decoded video planes to interleaved RGB8, written straight into the caller's buffer.
//!
//! Integer arithmetic with coefficients rounded once from the standards' constants, so every
//! machine gives the same bytes (a SIMD converter's rounding may differ by CPU).

/// The YCbCr matrix a stream was encoded with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColourMatrix {
    /// ITU-R BT.601 (standard definition, most webcams' MJPEG and H.264).
    Bt601,
    /// ITU-R BT.709 (HD).
    Bt709,
    /// ITU-R BT.2020.
    Bt2020,
}

/// One YCbCr -> RGB conversion as fixed-point (16 fractional bits) coefficients: per pixel
/// four integer multiply-adds, three shifts and three clamps, sixteen pixels at a time in
/// SIMD lanes (lookup tables, one load per term, cost twice as much: they cannot be
/// vectorised).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Conversion {
    /// Luma's offset and gain.
    y_offset: i32,
    y_gain: i32,
    /// Chroma gains: R from Cr, G from Cb and from Cr, B from Cb.
    rv: i32,
    gu: i32,
    gv: i32,
    bu: i32,
}

const ONE: f64 = 65536.0;

impl Conversion {
    /// The conversion for `matrix`, limited range (Y 16..235, Cb/Cr 16..240) unless
    /// `full_range`.
    pub fn new(matrix: ColourMatrix, full_range: bool) -> Conversion {
        let (kr, kb) = match matrix {
            ColourMatrix::Bt601 => (0.299, 0.114),
            ColourMatrix::Bt709 => (0.2126, 0.0722),
            ColourMatrix::Bt2020 => (0.2627, 0.0593),
        };
        let kg = 1.0 - kr - kb;
        let (y_offset, y_gain, c_gain) = if full_range { (0, 1.0, 1.0) } else { (16, 255.0 / 219.0, 255.0 / 224.0) };
        let fixed = |x: f64| (x * ONE).round() as i32;
        Conversion {
            y_offset,
            y_gain: fixed(y_gain),
            rv: fixed(2.0 * (1.0 - kr) * c_gain),
            gu: fixed(-2.0 * kb * (1.0 - kb) / kg * c_gain),
            gv: fixed(-2.0 * kr * (1.0 - kr) / kg * c_gain),
            bu: fixed(2.0 * (1.0 - kb) * c_gain),
        }
    }

    /// One pixel. No term overflows: at most 255 x 2^17 each.
    #[inline(always)]
    fn rgb(&self, y: u8, u: u8, v: u8) -> [u8; 3] {
        let y = (i32::from(y) - self.y_offset) * self.y_gain + (1 << 15);
        let (u, v) = (i32::from(u) - 128, i32::from(v) - 128);
        let clamp = |x: i32| (x >> 16).clamp(0, 255) as u8;
        [clamp(y + self.rv * v), clamp(y + (self.gu * u + self.gv * v)), clamp(y + self.bu * u)]
    }
}

/// Pixels converted together, one per SIMD lane.
const BLOCK: usize = 16;

handflow_protocol::vectorised_fn! {
    /// One row into interleaved RGB8, chroma shared by `1 << chroma_shift` pixels across
    /// (0 or 1; the caller checked): whole blocks of [`BLOCK`] pixels computed in lanes and
    /// then interleaved, then the row's tail pixel by pixel, with the same arithmetic.
    fn convert_row(c: &Conversion, chroma_shift: u32, y_row: &[u8], u_row: &[u8], v_row: &[u8], out: &mut [u8]) {
        let done = match chroma_shift {
            0 => convert_blocks::<0>(c, y_row, u_row, v_row, out),
            _ => convert_blocks::<1>(c, y_row, u_row, v_row, out),
        };
        for (x, pixel) in out.chunks_exact_mut(3).enumerate().skip(done) {
            let k = x >> chroma_shift;
            pixel.copy_from_slice(&c.rgb(y_row[x], u_row[k], v_row[k]));
        }
    }
}

/// The whole blocks of [`convert_row`]; returns the pixels done. The chroma shift is a
/// constant so each lane's chroma index is too.
#[inline(always)]
fn convert_blocks<const SHIFT: u32>(c: &Conversion, y_row: &[u8], u_row: &[u8], v_row: &[u8], out: &mut [u8]) -> usize {
    let blocks = y_row.len() / BLOCK;
    let chroma = BLOCK >> SHIFT;
    for b in 0..blocks {
        let ys = &y_row[b * BLOCK..(b + 1) * BLOCK];
        let (us, vs) = (&u_row[b * chroma..(b + 1) * chroma], &v_row[b * chroma..(b + 1) * chroma]);
        let mut planar = [[0u8; BLOCK]; 3];
        for i in 0..BLOCK {
            let [r, g, bl] = c.rgb(ys[i], us[i >> SHIFT], vs[i >> SHIFT]);
            (planar[0][i], planar[1][i], planar[2][i]) = (r, g, bl);
        }
        let o = &mut out[3 * b * BLOCK..3 * (b + 1) * BLOCK];
        for i in 0..BLOCK {
            o[3 * i] = planar[0][i];
            o[3 * i + 1] = planar[1][i];
            o[3 * i + 2] = planar[2][i];
        }
    }
    blocks * BLOCK
}

/// Three planes (Y, Cb, Cr) with their row strides; chroma is subsampled by `1 <<
/// chroma_shift.0` across and `1 << chroma_shift.1` down (I420: (1, 1); 4:2:2: (1, 0); 4:4:4:
/// (0, 0)).
pub struct Planes<'a> {
    /// `(data, stride)` of Y, Cb and Cr.
    pub planes: [(&'a [u8], usize); 3],
    /// Subsampling shifts of the chroma planes, across and down.
    pub chroma_shift: (u32, u32),
}

/// Converts planar YCbCr of `width` x `height` into interleaved RGB8 in `dst`.
pub fn planar_to_rgb(
    src: &Planes<'_>,
    width: usize,
    height: usize,
    conversion: &Conversion,
    dst: &mut [u8],
) -> Result<(), String> {
    if dst.len() != width * height * 3 {
        return Err(format!("destination holds {} bytes, {} needed", dst.len(), width * height * 3));
    }
    let (sx, sy) = src.chroma_shift;
    let chroma_width = (width + (1 << sx) - 1) >> sx;
    let chroma_height = (height + (1 << sy) - 1) >> sy;
    let [(y_plane, y_stride), (u_plane, u_stride), (v_plane, v_stride)] = src.planes;
    let fits = |plane: &[u8], stride: usize, w: usize, h: usize| {
        h == 0 || (stride >= w && plane.len() >= (h - 1) * stride + w)
    };
    if !fits(y_plane, y_stride, width, height)
        || !fits(u_plane, u_stride, chroma_width, chroma_height)
        || !fits(v_plane, v_stride, chroma_width, chroma_height)
    {
        return Err("the decoded planes are smaller than the frame".into());
    }
    if sx > 1 {
        return Err(format!("chroma subsampled by {} across: only 1 and 2 are known", 1 << sx));
    }
    for (row, out) in dst.chunks_exact_mut(width * 3).enumerate() {
        let y_row = &y_plane[row * y_stride..row * y_stride + width];
        let c = (row >> sy) * u_stride;
        let u_row = &u_plane[c..c + chroma_width];
        let c = (row >> sy) * v_stride;
        let v_row = &v_plane[c..c + chroma_width];
        convert_row(conversion, sx, y_row, u_row, v_row, out);
    }
    Ok(())
}

/// Copies `height` rows of packed RGB8 with row stride `stride` into tightly packed `dst`.
pub fn copy_rgb_rows(src: &[u8], stride: usize, width: usize, height: usize, dst: &mut [u8]) -> Result<(), String> {
    let row = width * 3;
    if dst.len() != row * height {
        return Err(format!("destination holds {} bytes, {} needed", dst.len(), row * height));
    }
    if height > 0 && (stride < row || src.len() < (height - 1) * stride + row) {
        return Err("the decoded image is smaller than the frame".into());
    }
    for (y, out) in dst.chunks_exact_mut(row).enumerate() {
        out.copy_from_slice(&src[y * stride..y * stride + row]);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limited_range_black_white_and_primaries() {
        let c = Conversion::new(ColourMatrix::Bt601, false);
        assert_eq!(c.rgb(16, 128, 128), [0, 0, 0]);
        assert_eq!(c.rgb(235, 128, 128), [255, 255, 255]);
        // BT.601 red in limited range: Y 81, Cb 90, Cr 240.
        let red = c.rgb(81, 90, 240);
        assert!(red[0] >= 253 && red[1] <= 2 && red[2] <= 2, "{red:?}");
        let full = Conversion::new(ColourMatrix::Bt709, true);
        assert_eq!(full.rgb(0, 128, 128), [0, 0, 0]);
        assert_eq!(full.rgb(255, 128, 128), [255, 255, 255]);
    }

    #[test]
    fn chroma_is_shared_by_the_pixels_it_covers_and_strides_are_honoured() {
        // 3x2 frame, I420 (chroma 2x1), Y rows padded to stride 4.
        let y = [16, 235, 16, 0, 235, 16, 235, 0];
        let u = [128, 90];
        let v = [128, 240];
        let planes = Planes { planes: [(&y, 4), (&u, 2), (&v, 2)], chroma_shift: (1, 1) };
        let mut dst = vec![0u8; 3 * 2 * 3];
        planar_to_rgb(&planes, 3, 2, &Conversion::new(ColourMatrix::Bt601, false), &mut dst).unwrap();
        assert_eq!(&dst[..6], &[0, 0, 0, 255, 255, 255], "first two pixels share neutral chroma");
        assert!(dst[6] > 100 && dst[8] < 60, "the third pixel takes the second (red) chroma sample: {:?}", &dst[6..9]);
        let mut short = vec![0u8; 5];
        assert!(planar_to_rgb(&planes, 3, 2, &Conversion::new(ColourMatrix::Bt601, false), &mut short).is_err());
    }

    #[test]
    fn blocks_and_row_tails_convert_as_each_pixel_alone() {
        // Pseudo-random planes, widths with and without a tail after the whole blocks.
        let mut state = 0x9e37_79b9u32;
        let mut byte = move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            (state >> 24) as u8
        };
        for (width, shift) in [(16usize, 1u32), (37, 1), (50, 0), (7, 1), (33, 0)] {
            let height = 3;
            let cw = (width + (1 << shift) - 1) >> shift;
            let y: Vec<u8> = (0..width * height).map(|_| byte()).collect();
            let u: Vec<u8> = (0..cw * height).map(|_| byte()).collect();
            let v: Vec<u8> = (0..cw * height).map(|_| byte()).collect();
            let planes = Planes { planes: [(&y, width), (&u, cw), (&v, cw)], chroma_shift: (shift, 0) };
            for (matrix, full) in [(ColourMatrix::Bt601, false), (ColourMatrix::Bt709, true)] {
                let c = Conversion::new(matrix, full);
                let mut dst = vec![0u8; width * height * 3];
                planar_to_rgb(&planes, width, height, &c, &mut dst).unwrap();
                for (i, px) in dst.chunks_exact(3).enumerate() {
                    let (row, x) = (i / width, i % width);
                    let k = row * cw + (x >> shift);
                    assert_eq!(px, c.rgb(y[i], u[k], v[k]), "width {width}, pixel {i}");
                }
            }
        }
    }

    #[test]
    fn chroma_subsampled_more_than_twice_across_is_refused() {
        let (y, u, v) = ([0u8; 8], [128u8; 2], [128u8; 2]);
        let planes = Planes { planes: [(&y, 8), (&u, 2), (&v, 2)], chroma_shift: (2, 0) };
        let mut dst = vec![0u8; 8 * 3];
        let e = planar_to_rgb(&planes, 8, 1, &Conversion::new(ColourMatrix::Bt601, false), &mut dst).unwrap_err();
        assert!(e.contains("chroma"), "{e}");
    }

    #[test]
    fn rgb_rows_drop_their_padding() {
        let src = [1, 2, 3, 9, 4, 5, 6, 9];
        let mut dst = [0u8; 6];
        copy_rgb_rows(&src, 4, 1, 2, &mut dst).unwrap();
        assert_eq!(dst, [1, 2, 3, 4, 5, 6]);
        assert!(copy_rgb_rows(&src[..6], 4, 1, 2, &mut dst).is_err());
    }
}
