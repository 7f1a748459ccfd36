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

/// One YCbCr -> RGB conversion as lookup tables of fixed-point (16 fractional bits) terms:
/// per pixel three additions, three shifts and three clamps.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Conversion {
    /// Luma's contribution (offset and gain, plus the rounding half).
    y: [i32; 256],
    r_from_v: [i32; 256],
    g_from_uv: [[i32; 256]; 2],
    b_from_u: [i32; 256],
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
        let (y_gain, rv, gu, gv, bu) = (
            fixed(y_gain),
            fixed(2.0 * (1.0 - kr) * c_gain),
            fixed(-2.0 * kb * (1.0 - kb) / kg * c_gain),
            fixed(-2.0 * kr * (1.0 - kr) / kg * c_gain),
            fixed(2.0 * (1.0 - kb) * c_gain),
        );
        let table = |f: &dyn Fn(i32) -> i32| -> [i32; 256] { std::array::from_fn(|i| f(i as i32)) };
        Conversion {
            y: table(&|y| (y - y_offset) * y_gain + (1 << 15)),
            r_from_v: table(&|v| rv * (v - 128)),
            g_from_uv: [table(&|u| gu * (u - 128)), table(&|v| gv * (v - 128))],
            b_from_u: table(&|u| bu * (u - 128)),
        }
    }

    /// The three chroma terms of one chroma sample.
    #[inline(always)]
    fn chroma(&self, u: u8, v: u8) -> [i32; 3] {
        [
            self.r_from_v[usize::from(v)],
            self.g_from_uv[0][usize::from(u)] + self.g_from_uv[1][usize::from(v)],
            self.b_from_u[usize::from(u)],
        ]
    }

    #[inline(always)]
    fn pixel(&self, y: u8, chroma: [i32; 3], out: &mut [u8]) {
        let y = self.y[usize::from(y)];
        let clamp = |x: i32| (x >> 16).clamp(0, 255) as u8;
        out[0] = clamp(y + chroma[0]);
        out[1] = clamp(y + chroma[1]);
        out[2] = clamp(y + chroma[2]);
    }

    #[cfg(test)]
    fn rgb(&self, y: u8, u: u8, v: u8) -> [u8; 3] {
        let mut out = [0u8; 3];
        self.pixel(y, self.chroma(u, v), &mut out);
        out
    }
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
    // Each chroma sample's terms are computed once for the `1 << sx` pixels it covers.
    let run = 1usize << sx;
    for (row, out) in dst.chunks_exact_mut(width * 3).enumerate() {
        let y_row = &y_plane[row * y_stride..row * y_stride + width];
        let c = (row >> sy) * u_stride;
        let u_row = &u_plane[c..c + chroma_width];
        let c = (row >> sy) * v_stride;
        let v_row = &v_plane[c..c + chroma_width];
        for (((pixels, ys), &u), &v) in out.chunks_mut(3 * run).zip(y_row.chunks(run)).zip(u_row).zip(v_row) {
            let chroma = conversion.chroma(u, v);
            for (pixel, &y) in pixels.chunks_exact_mut(3).zip(ys) {
                conversion.pixel(y, chroma, pixel);
            }
        }
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
    fn rgb_rows_drop_their_padding() {
        let src = [1, 2, 3, 9, 4, 5, 6, 9];
        let mut dst = [0u8; 6];
        copy_rgb_rows(&src, 4, 1, 2, &mut dst).unwrap();
        assert_eq!(dst, [1, 2, 3, 4, 5, 6]);
        assert!(copy_rgb_rows(&src[..6], 4, 1, 2, &mut dst).is_err());
    }
}
