//! Which vector unit the voxel walks use: the widest the CPU has, unless capped (benches compare
//! the portable build side by side with the wider ones). Every level computes the same `f64`
//! arithmetic (no fused multiply-add is ever formed), so results are identical across levels.

use std::sync::atomic::{AtomicU8, Ordering};

/// A vector instruction set the walk is compiled for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Level {
    /// The build's baseline target (SSE2 on x86-64).
    Portable = 0,
    /// AVX2 (x86-64).
    Avx2 = 1,
    /// AVX-512 F/VL/DQ/BW (x86-64).
    Avx512 = 2,
}

/// Highest level allowed; `u8::MAX` = no cap.
static CAP: AtomicU8 = AtomicU8::new(u8::MAX);

/// The best level this CPU supports.
pub fn detected() -> Level {
    #[cfg(target_arch = "x86_64")]
    {
        let avx2 = std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
            && std::arch::is_x86_feature_detected!("bmi1")
            && std::arch::is_x86_feature_detected!("bmi2")
            && std::arch::is_x86_feature_detected!("popcnt")
            && std::arch::is_x86_feature_detected!("lzcnt");
        let avx512 = avx2
            && std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512vl")
            && std::arch::is_x86_feature_detected!("avx512dq")
            && std::arch::is_x86_feature_detected!("avx512bw");
        if avx512 {
            return Level::Avx512;
        }
        if avx2 {
            return Level::Avx2;
        }
    }
    Level::Portable
}

/// Caps the level the walks use in this process (for side-by-side measurements).
pub fn set_cap(cap: Level) {
    CAP.store(cap as u8, Ordering::Relaxed);
}

/// The level the walks use: the detected one, capped.
pub fn level() -> Level {
    let cap = CAP.load(Ordering::Relaxed);
    let level = detected();
    if (level as u8) <= cap {
        return level;
    }
    match cap {
        0 => Level::Portable,
        1 => Level::Avx2,
        _ => Level::Avx512,
    }
}

impl Level {
    /// `portable`, `avx2` or `avx512`.
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "portable" => Some(Self::Portable),
            "avx2" => Some(Self::Avx2),
            "avx512" => Some(Self::Avx512),
            _ => None,
        }
    }
}
