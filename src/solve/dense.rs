//! Small dense linear systems (the normal equations of the few-parameter fits: planar trends,
//! registrations, the distortion fit), solved in `f64`.

/// Solves `a·x = b` (`n × n`, `a` row-major) by Gauss–Jordan elimination with partial pivoting;
/// `None` when a pivot's magnitude falls below `tiny` (a singular or degenerate fit). Columns
/// left of the pivot are already eliminated and are not touched again.
pub fn solve(mut a: Vec<Vec<f64>>, mut b: Vec<f64>, tiny: f64) -> Option<Vec<f64>> {
    let n = b.len();
    for i in 0..n {
        let piv = (i..n).max_by(|&x, &y| a[x][i].abs().total_cmp(&a[y][i].abs()))?;
        if a[piv][i].abs() < tiny {
            return None;
        }
        a.swap(i, piv);
        b.swap(i, piv);
        for r in 0..n {
            if r != i {
                let f = a[r][i] / a[i][i];
                if f != 0.0 {
                    for k in i..n {
                        a[r][k] -= f * a[i][k];
                    }
                    b[r] -= f * b[i];
                }
            }
        }
    }
    Some((0..n).map(|i| b[i] / a[i][i]).collect())
}

/// [`solve`] for a fixed-size system held in arrays.
pub fn gauss_jordan<const N: usize>(a: [[f64; N]; N], b: [f64; N], tiny: f64) -> Option<[f64; N]> {
    let x = solve(a.iter().map(|r| r.to_vec()).collect(), b.to_vec(), tiny)?;
    Some(std::array::from_fn(|i| x[i]))
}

/// An ordinary least-squares fit by the normal equations ([`least_squares`]).
pub struct LeastSquares {
    /// The solution `p` of `min Σ_i (a_i·p − d_i)²`.
    pub p: Vec<f64>,
    /// The residual mean square `Σ_i (d_i − a_i·p)² / (n − N)` (`n` rows, `N` unknowns).
    pub s2: f64,
    normal: Vec<Vec<f64>>,
    tiny: f64,
}

impl LeastSquares {
    /// Column `i` of `(AᵀA)⁻¹`; times [`LeastSquares::s2`] it is the covariance of `p` with
    /// `p_i`. `None` where the system is singular.
    pub fn inverse_column(&self, i: usize) -> Option<Vec<f64>> {
        solve(self.normal.clone(), (0..self.p.len()).map(|j| f64::from(u8::from(i == j))).collect(), self.tiny)
    }
}

/// Least squares of `rows` (`(a_i, d_i)`: `a_i·p ≈ d_i`, `N` unknowns) by the normal
/// equations `AᵀA p = Aᵀd` ([`solve`] with `tiny`); `None` when the system is singular or there
/// are not more rows than unknowns.
pub fn least_squares<const N: usize>(rows: &[([f64; N], f64)], tiny: f64) -> Option<LeastSquares> {
    if rows.len() <= N {
        return None;
    }
    let mut ata = vec![vec![0.0f64; N]; N];
    let mut atb = vec![0.0f64; N];
    for (row, d) in rows {
        for i in 0..N {
            atb[i] += row[i] * d;
            for j in 0..N {
                ata[i][j] += row[i] * row[j];
            }
        }
    }
    let p = solve(ata.clone(), atb, tiny)?;
    let ss: f64 = rows.iter().map(|(row, d)| (d - (0..N).map(|i| row[i] * p[i]).sum::<f64>()).powi(2)).sum();
    Some(LeastSquares { p, s2: ss / (rows.len() - N) as f64, normal: ata, tiny })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solves_a_system_that_needs_pivoting_and_refuses_a_singular_one() {
        // a zero on the first diagonal forces a row swap
        let a = [[0.0, 2.0, 1.0], [1.0, 1.0, 0.0], [3.0, 0.0, 1.0]];
        let x = [1.5, -2.0, 0.25];
        let b: [f64; 3] = std::array::from_fn(|i| (0..3).map(|j| a[i][j] * x[j]).sum());
        let got = gauss_jordan(a, b, 1e-12).unwrap();
        for i in 0..3 {
            assert!((got[i] - x[i]).abs() < 1e-12, "{got:?}");
        }
        assert!(gauss_jordan([[1.0, 2.0], [2.0, 4.0]], [1.0, 2.0], 1e-12).is_none());
    }

    /// A line through exact points has zero residual; with one point off, `s2` is its squared
    /// offset's share and the inverse columns are `(AᵀA)⁻¹`.
    #[test]
    fn least_squares_solution_residual_and_inverse() {
        let rows: Vec<([f64; 2], f64)> = (0..5).map(|x| ([x as f64, 1.0], 2.0 * x as f64 + 1.0)).collect();
        let f = least_squares(&rows, 1e-300).unwrap();
        assert!((f.p[0] - 2.0).abs() < 1e-12 && (f.p[1] - 1.0).abs() < 1e-12 && f.s2 < 1e-24, "{:?} {}", f.p, f.s2);
        // AᵀA = [[30, 10], [10, 5]]: its inverse is [[5, −10], [−10, 30]] / 50
        let (c0, c1) = (f.inverse_column(0).unwrap(), f.inverse_column(1).unwrap());
        for (got, want) in [(c0[0], 0.1), (c0[1], -0.2), (c1[0], -0.2), (c1[1], 0.6)] {
            assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        }
        assert!(least_squares(&rows[..2], 1e-300).is_none(), "no more rows than unknowns");
    }
}
