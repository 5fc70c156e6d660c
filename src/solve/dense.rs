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
}
