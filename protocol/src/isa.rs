//! Runtime choice of instruction set for the hot loops of every service.
//!
//! Release builds target baseline x86-64 (SSE2) so that one binary runs on any x86-64
//! machine. The matching cost and the image filters work on four-lane colour texels, where
//! AVX2 (x86-64-v3, every x86-64 CPU since about 2015) saves a register copy per operation
//! (three-operand forms) and holds two texels per register: measured on `signer-3cam`, the
//! engine runs 1.2 to 1.3x faster with these functions compiled for it, as fast as a whole
//! binary built for x86-64-v3 (BENCHMARKS.md); the decoder converts video frames to RGB 2.4x
//! faster. [`vectorised_fn`](crate::vectorised_fn) defines functions compiled for AVX2 and
//! FMA when the CPU has them, and baseline code otherwise.

/// Defines a function whose body is compiled twice, for baseline x86-64 and for AVX2 with
/// FMA, and which runs the second when the CPU has both (a cached check per call, so put it
/// around work of at least microseconds). Everything the body calls must be inlined into it
/// (`#[inline(always)]`) to be compiled for those features too; calls that are not inlined
/// run their baseline code. Both compute the same bits: Rust fuses a multiply and an add
/// only when asked (`mul_add`, which a body meant to match bit for bit must not use).
#[macro_export]
macro_rules! vectorised_fn {
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        $(#[$meta])*
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            // The copies take the outer function's arguments as they are; lints on the
            // argument list are the outer function's.
            #[allow(clippy::too_many_arguments)]
            #[inline(always)]
            fn body($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma")]
            #[allow(clippy::too_many_arguments)]
            fn avx2_fma($($arg: $ty),*) $(-> $ret)? {
                body($($arg),*)
            }
            #[cfg(target_arch = "x86_64")]
            if $crate::isa::has_avx2_fma() {
                // SAFETY: the CPU was just checked for both features `avx2_fma` is compiled for.
                #[allow(unsafe_code)]
                return unsafe { avx2_fma($($arg),*) };
            }
            body($($arg),*)
        }
    };
}

/// Whether the CPU has AVX2 and FMA (detected once by std, then a cached load).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub fn has_avx2_fma() -> bool {
    std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
}

/// Whether the CPU has AVX2 and FMA; never on other architectures.
#[cfg(not(target_arch = "x86_64"))]
pub fn has_avx2_fma() -> bool {
    false
}

#[cfg(test)]
mod tests {
    crate::vectorised_fn! {
        fn dot(a: &[f32], b: &[f32]) -> f32 {
            a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>()
        }
    }

    #[test]
    fn the_dispatched_function_computes_what_its_body_does() {
        // No `mul_add` in the body: the two paths agree to the bit.
        let a: Vec<f32> = (0..1000).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..1000).map(|i| (i as f32 * 0.11).cos()).collect();
        let plain = a.iter().zip(&b).map(|(x, y)| x * y).sum::<f32>();
        let fast = dot(&a, &b);
        assert_eq!(plain.to_bits(), fast.to_bits(), "{plain} vs {fast}");
    }
}
