//! Run-time instruction-set dispatch for the hot loops.
//!
//! The kernels (window sampling, HOG, tree routing, `W` sums) are plain Rust written as fixed-width lane
//! loops, `#[inline(always)]`, plus hand-written AVX-512 and AVX2 versions of them (`krfws::Avx512`,
//! `krfws::Avx2`) on x86-64 and NEON ones (`krfws::Neon`) on aarch64. The entry points ([`crate::krfws::Krfws::align`], [`crate::hog::hog_patch_dispatch`])
//! pick one with [`detected`], else the baseline build. Rust never fuses or reorders floating-point
//! operations on its own and the vector kernels perform the portable code's operations in its order, so
//! the results are bit-identical whichever path runs (tested in `tests/krfws_golden.rs` and next to each
//! kernel).

/// The vector instruction set the dispatching entry points use on this CPU.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// x86-64 with AVX-512F.
    Avx512,
    /// x86-64 with AVX2 and F16C.
    Avx2,
    /// aarch64 with NEON (Advanced SIMD): the hand-written NEON kernels.
    Neon,
    /// The build's baseline: the portable kernels as the compiler vectorises them (SSE2 on x86-64, NEON on
    /// aarch64).
    Baseline,
}

/// The best instruction set of this CPU among those we compile for (cached by the standard library).
pub fn detected() -> Isa {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx512f") {
            return Isa::Avx512;
        }
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("f16c") {
            return Isa::Avx2;
        }
    }
    #[cfg(target_arch = "aarch64")]
    if std::arch::is_aarch64_feature_detected!("neon") {
        return Isa::Neon;
    }
    Isa::Baseline
}
