//! Runtime dispatch of the fit's hot kernels to the widest SIMD the CPU has.
//!
//! The binning pass, the binned normal equations and the binned cost are loops of constant
//! length over independent lanes that the compiler vectorises; for the x86-64 baseline that is
//! SSE2's two f64 lanes. [`wide`] runs a closure compiled again with AVX2 (four lanes) or
//! AVX-512 (eight) when the CPU has them, detected at run time (pulp), so one binary serves CI
//! and users without those instructions. Results do not depend on the path: Rust never contracts
//! `a * b + c` into a fused multiply-add (only `mul_add` does, and the kernels do not call it),
//! vectorised loops keep each lane's operations and their order, and reductions across lanes are
//! written out in a fixed order; `fit::tests` checks the dispatched kernels against the
//! baseline bit for bit. The kernels a closure calls must be `#[inline(always)]`: a function
//! that is not inlined into the closure is compiled for the baseline only.

use std::sync::LazyLock;

/// The instruction set detected once per process (cheap to detect, but the kernels run tens of
/// times per curve).
static ARCH: LazyLock<pulp::Arch> = LazyLock::new(pulp::Arch::new);

/// A kernel to run under [`wide`]. Its `run` must be `#[inline(always)]`, and so must what it
/// calls in its hot loops: a closure would not do, since closures are not forced inline and the
/// compiler leaves a large one out of line, compiled for the baseline.
pub(crate) trait Kernel {
    /// What the kernel returns.
    type Output;
    /// The kernel's body.
    fn run(self) -> Self::Output;
}

/// pulp's entry point: `with_simd` is instantiated inside a function compiled for each
/// instruction set and inlines the kernel there.
struct Wide<K>(K);

impl<K: Kernel> pulp::WithSimd for Wide<K> {
    type Output = K::Output;
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) -> K::Output {
        self.0.run()
    }
}

/// Runs `kernel` compiled for the widest instruction set this CPU supports (AVX-512, AVX2,
/// else the baseline).
#[inline(always)]
pub(crate) fn wide<K: Kernel>(kernel: K) -> K::Output {
    ARCH.dispatch(Wide(kernel))
}
