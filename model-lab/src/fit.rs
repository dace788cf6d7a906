//! Levenberg–Marquardt for output-error fits, aware of block structure.
//!
//! Residuals come in blocks (one per motor). Most parameters belong to one motor and move only
//! that motor's residuals; a few (the extension's) are shared. Exploiting that, a Jacobian costs
//! one motor simulation per local parameter instead of a whole-robot simulation, and JᵀJ is
//! assembled from block products: analysing 8 motors costs about 8 times one motor, not 64.
//! Coupled models (heat flowing between motors) declare no local parameters and get the dense
//! treatment.

use nalgebra::{DMatrix, DVector};

/// A least-squares problem whose residuals are split in blocks.
pub trait Problem {
    /// Number of parameters.
    fn n_params(&self) -> usize;
    /// Number of residual blocks.
    fn n_blocks(&self) -> usize;
    /// The block a parameter is local to, or None when it moves every block.
    fn param_block(&self, j: usize) -> Option<usize>;
    /// All residuals, one vector per block (lengths must not depend on `p`).
    fn residuals(&self, p: &[f64], out: &mut [Vec<f64>]);
    /// Residuals of one block (only called for blocks of local parameters).
    fn block_residuals(&self, p: &[f64], b: usize, out: &mut Vec<f64>);
    /// Projects `p` onto the admissible set (bounds).
    fn clamp(&self, _p: &mut [f64]) {}
}

/// The outcome of a fit.
#[derive(Debug, Clone)]
pub struct Fitted {
    /// Parameters at the optimum.
    pub p: Vec<f64>,
    /// Sum of squared residuals there.
    pub sse: f64,
    /// Iterations used.
    pub iterations: usize,
}

fn sse(r: &[Vec<f64>]) -> f64 {
    r.iter().flatten().map(|v| v * v).sum()
}

enum Column {
    Local(usize, Vec<f64>),
    Global(Vec<Vec<f64>>),
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Column `j` of the forward-difference Jacobian at `p` (residuals `r`).
fn jacobian_column<P: Problem>(prob: &P, p: &[f64], r: &[Vec<f64>], j: usize) -> Column {
    let nb = prob.n_blocks();
    let mut q = p.to_vec();
    let h = 1e-6 * p[j].abs().max(1.0);
    q[j] += h;
    prob.clamp(&mut q);
    let mut h_eff = q[j] - p[j];
    if h_eff == 0.0 {
        // At the upper bound: step downward instead.
        q[j] = p[j] - h;
        prob.clamp(&mut q);
        h_eff = q[j] - p[j];
    }
    if h_eff == 0.0 {
        return Column::Local(0, vec![0.0; r[0].len()]);
    }
    match prob.param_block(j) {
        Some(b) => {
            let mut tmp = Vec::new();
            prob.block_residuals(&q, b, &mut tmp);
            let c = tmp
                .iter()
                .zip(&r[b])
                .map(|(a, b)| (a - b) / h_eff)
                .collect();
            Column::Local(b, c)
        }
        None => {
            let mut all = vec![Vec::new(); nb];
            prob.residuals(&q, &mut all);
            for (a, b) in all.iter_mut().zip(r) {
                for (x, y) in a.iter_mut().zip(b) {
                    *x = (*x - y) / h_eff;
                }
            }
            Column::Global(all)
        }
    }
}

/// Minimises the sum of squared residuals from `p0`, for at most `max_iter` iterations.
pub fn levenberg_marquardt<P: Problem + Sync>(prob: &P, p0: &[f64], max_iter: usize) -> Fitted {
    let n = prob.n_params();
    let nb = prob.n_blocks();
    let mut p = p0.to_vec();
    prob.clamp(&mut p);
    let mut r = vec![Vec::new(); nb];
    prob.residuals(&p, &mut r);
    let mut cost = sse(&r);
    let mut lambda = 1e-3;
    let mut iterations = 0;
    let mut trial_r = vec![Vec::new(); nb];
    while iterations < max_iter {
        iterations += 1;
        // Forward-difference Jacobian, one column per parameter, the columns spread over the
        // machine's cores (each column is independent; the result does not depend on the split).
        let threads = std::thread::available_parallelism()
            .map_or(1, |t| t.get())
            .min(n.max(1));
        let chunk = n.div_ceil(threads);
        let (p_ref, r_ref) = (&p, &r);
        let mut cols: Vec<Column> = Vec::with_capacity(n);
        if threads <= 1 {
            cols.extend((0..n).map(|j| jacobian_column(prob, p_ref, r_ref, j)));
        } else {
            let parts: Vec<Vec<Column>> = std::thread::scope(|sc| {
                let handles: Vec<_> = (0..threads)
                    .map(|t| {
                        sc.spawn(move || {
                            (t * chunk..((t + 1) * chunk).min(n))
                                .map(|j| jacobian_column(prob, p_ref, r_ref, j))
                                .collect::<Vec<Column>>()
                        })
                    })
                    .collect();
                handles
                    .into_iter()
                    .map(|h| h.join().unwrap_or_default())
                    .collect()
            });
            cols.extend(parts.into_iter().flatten());
        }
        if cols.len() != n {
            // A worker panicked (it cannot, short of a bug in the model): stop here.
            break;
        }
        let mut a = DMatrix::<f64>::zeros(n, n);
        let mut g = DVector::<f64>::zeros(n);
        for i in 0..n {
            g[i] = match &cols[i] {
                Column::Local(b, c) => dot(c, &r[*b]),
                Column::Global(c) => c.iter().zip(&r).map(|(c, r)| dot(c, r)).sum(),
            };
            for j in i..n {
                let v = match (&cols[i], &cols[j]) {
                    (Column::Local(bi, ci), Column::Local(bj, cj)) => {
                        if bi == bj {
                            dot(ci, cj)
                        } else {
                            0.0
                        }
                    }
                    (Column::Local(b, c), Column::Global(gl))
                    | (Column::Global(gl), Column::Local(b, c)) => dot(c, &gl[*b]),
                    (Column::Global(x), Column::Global(y)) => {
                        x.iter().zip(y).map(|(x, y)| dot(x, y)).sum()
                    }
                };
                a[(i, j)] = v;
                a[(j, i)] = v;
            }
        }
        let mut improved = false;
        loop {
            let mut m = a.clone();
            for i in 0..n {
                // Marquardt's scaling, with a floor so a parameter the data never touches
                // (a motor without readings in a segment) keeps the system solvable.
                m[(i, i)] += lambda * a[(i, i)].max(1e-9) + 1e-12;
            }
            let Some(ch) = m.cholesky() else {
                lambda *= 10.0;
                if lambda > 1e12 {
                    break;
                }
                continue;
            };
            let delta = ch.solve(&(-&g));
            let mut q: Vec<f64> = p.iter().zip(delta.iter()).map(|(a, d)| a + d).collect();
            prob.clamp(&mut q);
            prob.residuals(&q, &mut trial_r);
            let c = sse(&trial_r);
            if c.is_finite() && c < cost {
                let rel = (cost - c) / cost.max(1e-300);
                p = q;
                std::mem::swap(&mut r, &mut trial_r);
                cost = c;
                lambda = (lambda / 3.0).max(1e-12);
                improved = rel > 1e-8;
                break;
            }
            lambda *= 4.0;
            if lambda > 1e12 {
                break;
            }
        }
        if !improved {
            break;
        }
    }
    Fitted {
        p,
        sse: cost,
        iterations,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    /// Two blocks of exponential decays y = a_b·exp(−t/τ) with a shared τ.
    struct Decays {
        t: Vec<f64>,
        y: [Vec<f64>; 2],
    }

    impl Problem for Decays {
        fn n_params(&self) -> usize {
            3
        }
        fn n_blocks(&self) -> usize {
            2
        }
        fn param_block(&self, j: usize) -> Option<usize> {
            (j > 0).then(|| j - 1)
        }
        fn residuals(&self, p: &[f64], out: &mut [Vec<f64>]) {
            for (b, o) in out.iter_mut().enumerate() {
                self.block_residuals(p, b, o);
            }
        }
        fn block_residuals(&self, p: &[f64], b: usize, out: &mut Vec<f64>) {
            out.clear();
            out.extend(
                self.t
                    .iter()
                    .zip(&self.y[b])
                    .map(|(t, y)| p[1 + b] * (-t / p[0]).exp() - y),
            );
        }
    }

    #[test]
    fn recovers_shared_and_local_parameters() {
        let t: Vec<f64> = (0..50).map(|k| k as f64 * 0.2).collect();
        let y = [
            t.iter().map(|t| 3.0 * (-t / 2.5).exp()).collect(),
            t.iter().map(|t| -1.5 * (-t / 2.5).exp()).collect(),
        ];
        let f = levenberg_marquardt(&Decays { t, y }, &[1.0, 1.0, 1.0], 100);
        assert!((f.p[0] - 2.5).abs() < 1e-6, "{:?}", f.p);
        assert!((f.p[1] - 3.0).abs() < 1e-6 && (f.p[2] + 1.5).abs() < 1e-6);
        assert!(f.sse < 1e-12);
    }
}
