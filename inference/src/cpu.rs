//! What the CPU offers ONNX Runtime's int8 kernels: read by the precision rule (`crate::precision`) and by the
//! self-test (`crate::integrity`), which says why an int8 model answers badly on a CPU without VNNI.

/// The CPU's 8-bit dot-product instructions, as ONNX Runtime's int8 kernels use them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CpuInt8 {
    /// AVX-512 VNNI (`vpdpbusd` on 512-bit registers).
    pub avx512_vnni: bool,
    /// AVX-VNNI (the same on 256-bit registers, VEX-encoded).
    pub avx_vnni: bool,
}

impl CpuInt8 {
    /// This machine's flags.
    pub fn detect() -> Self {
        #[cfg(any(target_arch = "x86", target_arch = "x86_64"))]
        {
            Self {
                avx512_vnni: std::arch::is_x86_feature_detected!("avx512vnni"),
                avx_vnni: std::arch::is_x86_feature_detected!("avxvnni"),
            }
        }
        #[cfg(not(any(target_arch = "x86", target_arch = "x86_64")))]
        {
            Self::default()
        }
    }

    /// Whether int8 convolutions are one instruction per dot product here.
    pub fn has_vnni(self) -> bool {
        self.avx512_vnni || self.avx_vnni
    }

    /// The best of the flags, as the log and metrics name it (`none` without either).
    pub fn label(self) -> &'static str {
        if self.avx512_vnni {
            "avx512_vnni"
        } else if self.avx_vnni {
            "avx_vnni"
        } else {
            "none"
        }
    }
}
