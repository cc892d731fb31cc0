//! Test support shared by unit tests, integration tests and benchmarks' self-checks:
//! one tolerance type, closeness assertions that print index/actual/expected, and
//! central finite differences in f64.

use std::fmt;

/// Relative + absolute tolerance: `|a - e| <= abs + rel * |e|` element-wise.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tolerance {
    pub rel: f64,
    pub abs: f64,
}

impl Tolerance {
    pub const fn new(rel: f64, abs: f64) -> Self {
        Self { rel, abs }
    }
    /// f64 reference vs f64 reference (analytic gradients vs finite differences in f64).
    pub const F64_GRAD: Self = Self::new(1e-5, 1e-7);
    /// f32 kernels vs their f32 CPU twin (same algorithm, different summation order).
    pub const F32_KERNEL: Self = Self::new(1e-4, 1e-5);
    /// WGSL on a GPU/lavapipe vs the cpu backend: transcendental functions differ by a few ulp.
    pub const GPU_VS_CPU: Self = Self::new(2e-3, 1e-4);

    pub fn ok(&self, actual: f64, expected: f64) -> bool {
        if actual.is_nan() || expected.is_nan() {
            return false;
        }
        (actual - expected).abs() <= self.abs + self.rel * expected.abs()
    }
}

/// A failed closeness check, with the worst element.
#[derive(Debug)]
pub struct Mismatch {
    pub what: String,
    pub index: usize,
    pub actual: f64,
    pub expected: f64,
    pub failures: usize,
    pub len: usize,
    pub tol: Tolerance,
}

impl fmt::Display for Mismatch {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}: {} of {} elements out of tolerance (rel {:e}, abs {:e}); worst at index {}: actual {:e}, expected {:e}, |diff| {:e}",
            self.what,
            self.failures,
            self.len,
            self.tol.rel,
            self.tol.abs,
            self.index,
            self.actual,
            self.expected,
            (self.actual - self.expected).abs()
        )
    }
}

/// Compare two sequences element-wise. Returns the worst mismatch (by excess over tolerance).
pub fn compare<A, E>(what: &str, actual: &[A], expected: &[E], tol: Tolerance) -> Result<(), Mismatch>
where
    A: Copy + Into<f64>,
    E: Copy + Into<f64>,
{
    assert_eq!(actual.len(), expected.len(), "{what}: length mismatch");
    let mut failures = 0;
    let mut worst: Option<(usize, f64, f64, f64)> = None;
    for (i, (&a, &e)) in actual.iter().zip(expected).enumerate() {
        let (a, e): (f64, f64) = (a.into(), e.into());
        if !tol.ok(a, e) {
            failures += 1;
            let excess = if a.is_nan() || e.is_nan() { f64::INFINITY } else { (a - e).abs() - tol.abs - tol.rel * e.abs() };
            if worst.is_none_or(|w| excess > w.3) {
                worst = Some((i, a, e, excess));
            }
        }
    }
    match worst {
        None => Ok(()),
        Some((index, actual, expected_v, _)) => Err(Mismatch {
            what: what.to_string(),
            index,
            actual,
            expected: expected_v,
            failures,
            len: expected.len(),
            tol,
        }),
    }
}

/// Panicking form of [`compare`] for tests.
#[track_caller]
pub fn assert_close<A, E>(what: &str, actual: &[A], expected: &[E], tol: Tolerance)
where
    A: Copy + Into<f64>,
    E: Copy + Into<f64>,
{
    if let Err(m) = compare(what, actual, expected, tol) {
        panic!("{m}");
    }
}

/// Central finite differences of a scalar function of `x` (f64), step `h` per coordinate.
pub fn finite_diff_grad(x: &[f64], h: f64, mut f: impl FnMut(&[f64]) -> f64) -> Vec<f64> {
    let mut xp = x.to_vec();
    (0..x.len())
        .map(|i| {
            let x0 = xp[i];
            xp[i] = x0 + h;
            let fp = f(&xp);
            xp[i] = x0 - h;
            let fm = f(&xp);
            xp[i] = x0;
            (fp - fm) / (2.0 * h)
        })
        .collect()
}

/// Check an analytic gradient against central finite differences of `f` at `x`.
#[track_caller]
pub fn check_grad(what: &str, x: &[f64], analytic: &[f64], h: f64, tol: Tolerance, f: impl FnMut(&[f64]) -> f64) {
    let numeric = finite_diff_grad(x, h, f);
    assert_close(what, analytic, &numeric, tol);
}

/// Assert every value is finite, naming the first offender.
#[track_caller]
pub fn assert_finite<T: Copy + Into<f64>>(what: &str, values: &[T]) {
    if let Some((i, v)) = values.iter().enumerate().find(|(_, v)| !(**v).into().is_finite()) {
        panic!("{what}: non-finite value {} at index {i} of {}", (*v).into(), values.len());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compare_reports_worst_index() {
        let err = compare("v", &[1.0f32, 2.0, 3.5], &[1.0f32, 2.0, 3.0], Tolerance::F32_KERNEL).unwrap_err();
        assert_eq!(err.index, 2);
        assert_eq!(err.failures, 1);
        assert_eq!(err.len, 3);
        assert!(compare("nan", &[f64::NAN], &[f64::NAN], Tolerance::F64_GRAD).is_err());
    }

    #[test]
    fn finite_differences_of_a_known_function() {
        let x = [0.3f64, -1.2];
        let f = |v: &[f64]| v[0].sin() * v[1] * v[1];
        let analytic = [x[0].cos() * x[1] * x[1], 2.0 * x[0].sin() * x[1]];
        check_grad("sin(x)y^2", &x, &analytic, 1e-5, Tolerance::F64_GRAD, f);
    }
}
