//! Small dense linear systems (the normal equations of the few-parameter fits: planar trends,
//! registrations, the distortion fit), solved in `f64`.

/// Solves `a·x = b` for an `N × N` system by Gauss–Jordan elimination with partial pivoting;
/// `None` when a pivot's magnitude falls below `tiny` (a singular or degenerate fit).
pub fn gauss_jordan<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N], tiny: f64) -> Option<[f64; N]> {
    for i in 0..N {
        let piv = (i..N).max_by(|&x, &y| a[x][i].abs().total_cmp(&a[y][i].abs()))?;
        if a[piv][i].abs() < tiny {
            return None;
        }
        a.swap(i, piv);
        b.swap(i, piv);
        for r in 0..N {
            if r != i {
                let f = a[r][i] / a[i][i];
                for k in 0..N {
                    a[r][k] -= f * a[i][k];
                }
                b[r] -= f * b[i];
            }
        }
    }
    Some(std::array::from_fn(|i| b[i] / a[i][i]))
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
