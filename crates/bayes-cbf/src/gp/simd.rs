//! Calls into faer, and the AVX state they leave behind.
//!
//! faer's SIMD kernels return with the upper halves of the AVX registers
//! dirty; on many x86 CPUs every later legacy-SSE instruction (libm's `exp`
//! entry point, scalar code compiled for the x86-64 baseline) then pays a
//! transition penalty. Measured here: a 200 × 200 RBF Gram matrix took
//! 3.3 ms after a faer call and 0.30 ms after `vzeroupper`. Every faer
//! operation in this crate (factorisations, triangular solves, inverses,
//! products, dot products, copies) therefore runs inside [`with_faer`],
//! which clears that state once the call returns.

/// Sets the threads of the dense linear algebra (faer's global
/// parallelism) for the whole process: `1` runs factorisations and solves
/// on the calling thread (what the benchmarks, the experiments and a
/// control loop on one core want), more uses a rayon pool of that many
/// threads. `0` is taken as `1`.
pub fn set_linear_algebra_threads(threads: usize) {
    faer::set_global_parallelism(if threads <= 1 {
        faer::Par::Seq
    } else {
        faer::Par::rayon(threads)
    });
}

/// Runs `f`, a call (or a short run of calls) into faer, then clears the
/// upper halves of the AVX registers (`vzeroupper`).
#[inline]
pub(crate) fn with_faer<R>(f: impl FnOnce() -> R) -> R {
    let out = f();
    clear_simd_state();
    out
}

/// `vzeroupper` where AVX is available; nothing elsewhere.
#[inline]
fn clear_simd_state() {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the `avx` feature was detected at run time.
            unsafe { std::arch::x86_64::_mm256_zeroupper() }
        }
    }
}
