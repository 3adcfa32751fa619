//! Tests of the sparse GPs against dense reference formulas (nalgebra), the exact GP and finite
//! differences.

use nalgebra::{DMatrix, DVector};

use super::*;
use crate::gp::tests::{data, theta};
use crate::gp::{GpWorkspace, MultiGp};

const METHODS: [SparseMethod; 2] = [SparseMethod::Vfe, SparseMethod::Fitc];

/// The objective, mean and variance at `d` from the dense N × N formulas.
fn dense(
    x: &[f64],
    y: &[f64],
    z: &[f64],
    th: &[f64],
    method: SparseMethod,
    d: &[f64],
) -> (f64, Vec<f64>, Vec<f64>) {
    let nd = th.len() - 2;
    let (n, m, k) = (y.len(), z.len() / nd, d.len() / nd);
    let ls: Vec<f64> = th[1..=nd].iter().map(|t| t.exp()).collect();
    let kern = SeArd::new(th[0].exp(), &ls).unwrap();
    let sig2 = (2.0 * th[nd + 1]).exp();
    let pt = |a: &[f64], i: usize| a[i * nd..(i + 1) * nd].to_vec();
    let cross = |a: &[f64], na: usize, b: &[f64], nb: usize| {
        DMatrix::from_fn(na, nb, |i, j| kern.eval(&pt(a, i), &pt(b, j)))
    };
    let kuu = cross(z, m, z, m);
    let kuf = cross(z, m, x, n);
    let kuu_chol = kuu.clone().cholesky().unwrap();
    let qff = kuf.transpose() * kuu_chol.solve(&kuf);
    let s2 = kern.variance();
    let lam: Vec<f64> = (0..n)
        .map(|i| match method {
            SparseMethod::Vfe => sig2,
            SparseMethod::Fitc => s2 - qff[(i, i)] + sig2,
        })
        .collect();
    let lam_m = DMatrix::from_diagonal(&DVector::from_vec(lam.clone()));
    let c = &qff + &lam_m;
    let yv = DVector::from_column_slice(y);
    let c_chol = c.clone().cholesky().unwrap();
    let logdet = 2.0 * c_chol.l().diagonal().iter().map(|v| v.ln()).sum::<f64>();
    let mut f = -0.5 * yv.dot(&c_chol.solve(&yv))
        - 0.5 * logdet
        - 0.5 * n as f64 * (2.0 * std::f64::consts::PI).ln();
    if method == SparseMethod::Vfe {
        f -= (0..n).map(|i| s2 - qff[(i, i)]).sum::<f64>() / (2.0 * sig2);
    }
    let lam_inv = lam_m.try_inverse().unwrap();
    let p_chol = (&kuu + &kuf * &lam_inv * kuf.transpose())
        .cholesky()
        .unwrap();
    let ks = cross(z, m, d, k);
    let mean = ks.transpose() * p_chol.solve(&(&kuf * &lam_inv * &yv));
    let var = (0..k)
        .map(|j| {
            let kc = ks.column(j).into_owned();
            s2 - kc.dot(&kuu_chol.solve(&kc)) + kc.dot(&p_chol.solve(&kc))
        })
        .collect();
    (f, mean.as_slice().to_vec(), var)
}

fn predict(gp: &SparseGp, d: &[f64]) -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
    let multi = SparseMultiGp {
        gps: vec![gp.clone()],
        mean: None,
        mean_rounding: vec![0.0],
    };
    let (k, nd) = (d.len() / gp.dim(), gp.dim());
    let (mut m, mut v) = (vec![0.0; k], vec![0.0; k]);
    let (mut dm, mut dv) = (vec![0.0; k * nd], vec![0.0; k * nd]);
    let mut ws = SparseWorkspace::default();
    multi
        .predict_with_gradients_into(d, &mut m, &mut v, &mut dm, &mut dv, &mut ws)
        .unwrap();
    (m, v, dm, dv)
}

/// m inducing points chosen greedily from `x` (well separated, as the package chooses them).
fn greedy(x: &[f64], nd: usize, m: usize) -> Vec<f64> {
    let idx = select_inducing(x, &theta(nd), m).unwrap();
    idx.iter()
        .flat_map(|&i| x[i * nd..(i + 1) * nd].to_vec())
        .collect()
}

/// The 2-norm condition number of K(Z, Z) at θ = `theta(n_d)`.
fn condition(z: &[f64], nd: usize) -> f64 {
    let th = theta(nd);
    let ls: Vec<f64> = th[1..=nd].iter().map(|t| t.exp()).collect();
    let kern = SeArd::new(th[0].exp(), &ls).unwrap();
    let m = z.len() / nd;
    let k = DMatrix::from_fn(m, m, |i, j| {
        kern.eval(&z[i * nd..(i + 1) * nd], &z[j * nd..(j + 1) * nd])
    });
    let sv = k.singular_values();
    sv.max() / sv.min()
}

fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs().max(1e-300)
}

#[test]
fn inducing_points_at_the_data_reproduce_the_exact_gp() {
    // The sparse formulas go through K(Z, Z)⁻¹, the exact GP through (K + σ_ε² I)⁻¹: with Z = X
    // they agree to about ε·cond(K); these 20 points give cond(K) < 1e5.
    let nd = 2;
    let (x, y) = data(20, nd, 1);
    assert!(condition(&x, nd) < 1e5, "{}", condition(&x, nd));
    let th = theta(nd);
    let exact = MultiGp::new(&x, &y, &th).unwrap();
    let (d, _) = data(6, nd, 7);
    let (mut me, mut ve) = (vec![0.0; 6], vec![0.0; 6]);
    exact
        .predict_into(&d, &mut me, &mut ve, &mut GpWorkspace::default())
        .unwrap();
    let lml = exact.gps()[0].log_marginal_likelihood();
    for method in METHODS {
        let gp = SparseGp::new(&x, &y, &x, &th, method).unwrap();
        assert_eq!(gp.jitter(), 0.0);
        assert!(
            rel(gp.objective(), lml) < 1e-8,
            "{method:?}: {} vs {lml}",
            gp.objective()
        );
        let (m, v, _, _) = predict(&gp, &d);
        for j in 0..6 {
            assert!(
                rel(m[j], me[j]) < 1e-8,
                "{method:?} mean {} vs {}",
                m[j],
                me[j]
            );
            assert!(
                rel(v[j], ve[j]) < 1e-8,
                "{method:?} var {} vs {}",
                v[j],
                ve[j]
            );
        }
    }
}

#[test]
fn objective_and_predictions_match_dense_formulas() {
    for (nd, n, m) in [(1, 30, 6), (2, 60, 12), (3, 1300, 15)] {
        let (x, y) = data(n, nd, nd as u64 + 10);
        let z = greedy(&x, nd, m);
        let (d, _) = data(5, nd, 5);
        let th = theta(nd);
        for method in METHODS {
            let gp = SparseGp::new(&x, &y, &z, &th, method).unwrap();
            let (f, me, ve) = dense(&x, &y, &z, &th, method, &d);
            assert!(
                rel(gp.objective(), f) < 1e-9,
                "{method:?} {} vs {f}",
                gp.objective()
            );
            let (mm, vv, _, _) = predict(&gp, &d);
            for j in 0..5 {
                assert!((mm[j] - me[j]).abs() < 1e-9 * (1.0 + me[j].abs()));
                assert!((vv[j] - ve[j]).abs() < 1e-9, "{} vs {}", vv[j], ve[j]);
            }
        }
    }
}

#[test]
fn objective_gradients_match_finite_differences() {
    let nd = 2;
    let (x, y) = data(700, nd, 3);
    let (z, _) = data(9, nd, 4);
    let th = theta(nd);
    for method in METHODS {
        let f = |t: &[f64], z: &[f64]| sparse_objective(&x, &y, z, t, method, false).unwrap().value;
        let obj = sparse_objective(&x, &y, &z, &th, method, true).unwrap();
        let h = 1e-6;
        for i in 0..th.len() {
            let (mut tp, mut tm) = (th.clone(), th.clone());
            tp[i] += h;
            tm[i] -= h;
            let fd = (f(&tp, &z) - f(&tm, &z)) / (2.0 * h);
            let g = obj.grad_theta[i];
            assert!(
                (fd - g).abs() < 1e-5 * (1.0 + fd.abs()),
                "{method:?} theta[{i}]: {fd} vs {g}"
            );
        }
        for i in 0..z.len() {
            let (mut zp, mut zm) = (z.clone(), z.clone());
            zp[i] += h;
            zm[i] -= h;
            let fd = (f(&th, &zp) - f(&th, &zm)) / (2.0 * h);
            let g = obj.grad_z[i];
            assert!(
                (fd - g).abs() < 1e-5 * (1.0 + fd.abs()),
                "{method:?} z[{i}]: {fd} vs {g}"
            );
        }
    }
}

#[test]
fn input_gradients_match_finite_differences() {
    let nd = 3;
    let (x, y) = data(80, nd, 5);
    let (z, _) = data(10, nd, 6);
    let (d, _) = data(4, nd, 8);
    for method in METHODS {
        let gp = SparseGp::new(&x, &y, &z, &theta(nd), method).unwrap();
        let (_, _, dm, dv) = predict(&gp, &d);
        let h = 1e-6;
        for l in 0..nd {
            let (mut dp, mut dn) = (d.clone(), d.clone());
            for j in 0..4 {
                dp[j * nd + l] += h;
                dn[j * nd + l] -= h;
            }
            let (mp, vp, _, _) = predict(&gp, &dp);
            let (mn, vn, _, _) = predict(&gp, &dn);
            for j in 0..4 {
                let (fm, fv) = ((mp[j] - mn[j]) / (2.0 * h), (vp[j] - vn[j]) / (2.0 * h));
                assert!(
                    (fm - dm[j * nd + l]).abs() < 1e-7,
                    "mean {fm} {}",
                    dm[j * nd + l]
                );
                assert!(
                    (fv - dv[j * nd + l]).abs() < 1e-7,
                    "var {fv} {}",
                    dv[j * nd + l]
                );
            }
        }
    }
}

#[test]
fn variance_returns_to_the_prior_far_from_the_data() {
    let nd = 2;
    let (x, y) = data(200, nd, 2);
    let z = greedy(&x, nd, 20);
    for method in METHODS {
        let gp = SparseGp::new(&x, &y, &z, &theta(nd), method).unwrap();
        // Far away, at 3 and 1.5 length-scales from the box, and at an inducing point.
        let d = [30.0, -40.0, -6.0, 0.0, -2.0 - 1.5 * 0.7, 0.0, z[0], z[1]];
        let (m, v, _, _) = predict(&gp, &d);
        let s2 = gp.kernel().variance();
        assert!((v[0] - s2).abs() < 1e-12 * s2 && m[0].abs() < 1e-12);
        assert!(v[1] > 0.95 * s2 && v[2] > v[3] && v[2] < v[1]);
        assert!(v[3] < 0.05 * s2, "{v:?}");
    }
}

#[test]
fn greedy_selection_skips_duplicates_and_stops_at_the_floor() {
    let nd = 1;
    // Three distinct values, each repeated: no more than three points carry information.
    let x: Vec<f64> = (0..30).map(|i| [0.0, 1.5, -2.0][i % 3]).collect();
    let idx = select_inducing(&x, &theta(nd), 10).unwrap();
    assert_eq!(idx.len(), 3);
    let mut vals: Vec<f64> = idx.iter().map(|&i| x[i]).collect();
    vals.sort_by(|a, b| a.partial_cmp(b).unwrap());
    assert_eq!(vals, vec![-2.0, 0.0, 1.5]);
    // On spread data it returns m distinct points.
    let (x, _) = data(100, 2, 3);
    let idx = select_inducing(&x, &theta(2), 25).unwrap();
    let mut s = idx.clone();
    s.sort();
    s.dedup();
    assert_eq!((idx.len(), s.len()), (25, 25));
}

#[test]
fn duplicated_inducing_points_use_jitter() {
    let nd = 1;
    let (x, y) = data(50, nd, 4);
    let z = vec![0.3, 0.3, -1.0, 1.0];
    for method in METHODS {
        let gp = SparseGp::new(&x, &y, &z, &theta(nd), method).unwrap();
        assert!(gp.jitter() > 0.0 && gp.jitter() <= 1e-6 * gp.kernel().variance());
        let (m, v, _, _) = predict(&gp, &[0.3]);
        assert!(m[0].is_finite() && v[0] >= 0.0);
    }
}

#[test]
fn multi_output_matches_single_outputs() {
    let (nd, q, n) = (2, 2, 50);
    let (x, y0) = data(n, nd, 1);
    let ymat: Vec<f64> = y0.iter().flat_map(|v| [*v, 2.0 * v + 1.0]).collect();
    let (z0, _) = data(7, nd, 2);
    let (z1, _) = data(5, nd, 3);
    let thetas: Vec<f64> = [theta(nd), theta(nd).iter().map(|t| t + 0.2).collect()].concat();
    let multi = SparseMultiGp::new(&x, &ymat, &[&z0, &z1], &thetas, SparseMethod::Fitc).unwrap();
    let (d, _) = data(3, nd, 9);
    let mut ws = SparseWorkspace::default();
    let (mut m, mut v) = (vec![0.0; 3 * q], vec![0.0; 3 * q]);
    multi.predict_into(&d, &mut m, &mut v, &mut ws).unwrap();
    let y1: Vec<f64> = y0.iter().map(|v| 2.0 * v + 1.0).collect();
    let single = SparseGp::new(&x, &y1, &z1, &thetas[4..], SparseMethod::Fitc).unwrap();
    let (m1, v1, _, _) = predict(&single, &d);
    for j in 0..3 {
        assert_eq!((m[j * q + 1], v[j * q + 1]), (m1[j], v1[j]));
    }
}

#[test]
fn prior_mean_adds_its_values_and_gradients_and_nothing_else() {
    let (nd, q, n, k) = (2, 2, 40, 4);
    let (x, y0) = data(n, nd, 4);
    let ymat: Vec<f64> = y0.iter().flat_map(|v| [*v, -v]).collect();
    let (z, _) = data(6, nd, 5);
    let thetas = [theta(nd), theta(nd)].concat();
    let plain = SparseMultiGp::new(&x, &ymat, &[&z, &z], &thetas, SparseMethod::Vfe).unwrap();
    // m_0 = 1 + 2 d0 − d1, m_1 = −3 + 0.5 d1.
    let coef = vec![1.0, 2.0, -1.0, -3.0, 0.0, 0.5];
    let with = plain
        .clone()
        .with_mean(AffineMean::new(q, nd, coef).unwrap())
        .unwrap();
    let (d, _) = data(k, nd, 6);
    let mut ws = SparseWorkspace::default();
    let run = |g: &SparseMultiGp, ws: &mut SparseWorkspace| {
        let mut out = vec![
            vec![0.0; k * q],
            vec![0.0; k * q],
            vec![0.0; k * q * nd],
            vec![0.0; k * q * nd],
        ];
        let [m, v, dm, dv] = &mut out[..] else {
            unreachable!()
        };
        g.predict_with_gradients_into(&d, m, v, dm, dv, ws).unwrap();
        out
    };
    let (a, b) = (run(&plain, &mut ws), run(&with, &mut ws));
    for j in 0..k {
        let (d0, d1) = (d[j * nd], d[j * nd + 1]);
        assert!((b[0][j * q] - a[0][j * q] - (1.0 + 2.0 * d0 - d1)).abs() < 1e-12);
        assert!((b[0][j * q + 1] - a[0][j * q + 1] - (-3.0 + 0.5 * d1)).abs() < 1e-12);
        assert_eq!(
            &b[2][j * q * nd..j * q * nd + 2],
            &[a[2][j * q * nd] + 2.0, a[2][j * q * nd + 1] - 1.0]
        );
    }
    assert_eq!(
        (&a[1], &a[3]),
        (&b[1], &b[3]),
        "the variances do not depend on the mean"
    );
    let mut mean_only = vec![0.0; k * q];
    with.predict_mean_into(&d, &mut mean_only, &mut ws).unwrap();
    assert_eq!(mean_only, b[0]);
    assert!(plain
        .with_mean(AffineMean::new(1, nd, vec![0.0; 3]).unwrap())
        .is_err());
}

#[test]
fn bad_input_is_rejected_with_the_argument_named() {
    let (x, y) = data(10, 2, 1);
    let z = x[..6].to_vec();
    let name = |r: Result<SparseGp>| match r {
        Err(Error::InvalidInput { arg, .. }) => arg,
        other => panic!("expected InvalidInput, got {other:?}"),
    };
    let vfe = SparseMethod::Vfe;
    assert_eq!(name(SparseGp::new(&x, &y, &z, &[0.0, 0.0], vfe)), "theta");
    assert_eq!(name(SparseGp::new(&x, &y, &z[..5], &theta(2), vfe)), "z");
    assert_eq!(name(SparseGp::new(&x, &y, &[], &theta(2), vfe)), "z");
    assert_eq!(
        name(SparseGp::new(&x, &y, &[f64::NAN, 0.0], &theta(2), vfe)),
        "z"
    );
    assert_eq!(name(SparseGp::new(&x[..19], &y, &z, &theta(2), vfe)), "x");
    assert_eq!(
        name(SparseGp::new(&x[..2], &y[..1], &z, &theta(2), vfe)),
        "y"
    );
    assert!(matches!(
        SparseMethod::parse("dtc"),
        Err(Error::InvalidInput { .. })
    ));
    assert_eq!(SparseMethod::parse("FITC").unwrap(), SparseMethod::Fitc);
    assert!(select_inducing(&x, &theta(2), 0).is_err());
    assert!(select_inducing(&x[..3], &theta(2), 2).is_err());
}

/// A replaced posterior N(μ, Σ) of the inducing outputs predicts J μ and σ_f² − J K Jᵀ + J Σ Jᵀ
/// (J = k(d, Z) K⁻¹, dense), J is the mean's derivative with respect to μ, and the GP's own
/// posterior predicts as the fit.
#[test]
fn replaced_inducing_posterior_predicts_as_the_dense_formulas() {
    let (nd, n, m) = (2, 60, 8);
    let (x, y) = data(n, nd, 31);
    let z = greedy(&x, nd, m);
    let (d, _) = data(6, nd, 32);
    let th = theta(nd);
    let fitted = SparseGp::new(&x, &y, &z, &th, SparseMethod::Vfe).unwrap();
    let (mu0, sigma0) = fitted.inducing_posterior();
    let mut same = fitted.clone();
    same.set_inducing_posterior(&mu0, sigma0.as_ref()).unwrap();
    let (a, b) = (predict(&fitted, &d), predict(&same, &d));
    for j in 0..6 {
        assert!(
            rel(b.0[j], a.0[j]) < 1e-9 && rel(b.1[j], a.1[j]) < 1e-7,
            "{j}"
        );
    }
    // Another posterior: shifted mean, covariance shrunk and correlated.
    let mu: Vec<f64> = mu0
        .iter()
        .enumerate()
        .map(|(i, v)| v + 0.1 * i as f64)
        .collect();
    let s = DMatrix::from_fn(m, m, |i, j| sigma0[(i, j)]);
    let c = DMatrix::from_fn(m, m, |i, j| 0.5 * (-((i as f64 - j as f64).powi(2))).exp());
    let sigma = &c * &s * c.transpose() + DMatrix::identity(m, m) * 1e-3;
    let mut gp = fitted.clone();
    let sf = faer::Mat::from_fn(m, m, |i, j| sigma[(i, j)]);
    gp.set_inducing_posterior(&mu, sf.as_ref()).unwrap();
    let (mean, var, _, _) = predict(&gp, &d);
    let kern = gp.kernel().clone();
    let pt = |a: &[f64], i: usize| a[i * nd..(i + 1) * nd].to_vec();
    let kuu = DMatrix::from_fn(m, m, |i, j| kern.eval(&pt(&z, i), &pt(&z, j)))
        + DMatrix::identity(m, m) * gp.jitter();
    let mut jac = vec![0.0; 6 * m];
    gp.inducing_jacobian_into(&d, &mut jac).unwrap();
    for k in 0..6 {
        let ks = DVector::from_fn(m, |i, _| kern.eval(&pt(&z, i), &pt(&d, k)));
        let jk = kuu.clone().cholesky().unwrap().solve(&ks);
        for i in 0..m {
            assert!((jac[k * m + i] - jk[i]).abs() < 1e-8 * (1.0 + jk[i].abs()));
        }
        let want_mean = jk.dot(&DVector::from_column_slice(&mu));
        let want_var = kern.variance() - jk.dot(&(&kuu * &jk)) + jk.dot(&(&sigma * &jk));
        assert!(
            (mean[k] - want_mean).abs() < 1e-9 * (1.0 + want_mean.abs()),
            "{k}"
        );
        assert!(
            (var[k] - want_var).abs() < 1e-9,
            "{k}: {} vs {want_var}",
            var[k]
        );
    }
    // Not positive definite: refused, the GP unchanged.
    let bad = faer::Mat::from_fn(m, m, |i, j| if i == j { -1.0 } else { 0.0 });
    let mut kept = gp.clone();
    let e = kept.set_inducing_posterior(&mu0, bad.as_ref()).unwrap_err();
    assert!(matches!(e, Error::Numerical(_)));
    assert_eq!(predict(&kept, &d).0, mean);
}

/// GPs giving the variance given the inducing outputs predict, with J, exactly what they predict
/// without it, and J is k(d, Z) K⁻¹ as computed on its own; GPs giving the posterior's variance
/// are refused.
#[test]
fn conditional_predictions_return_the_inducing_jacobians() {
    let (nd, q, n, k) = (2, 2, 50, 4);
    let (x, y0) = data(n, nd, 1);
    let ymat: Vec<f64> = y0.iter().flat_map(|v| [*v, 2.0 * v + 1.0]).collect();
    let (z0, _) = data(7, nd, 2);
    let (z1, _) = data(5, nd, 3);
    let thetas: Vec<f64> = [theta(nd), theta(nd).iter().map(|t| t + 0.2).collect()].concat();
    let mut multi =
        SparseMultiGp::new(&x, &ymat, &[&z0, &z1], &thetas, SparseMethod::Fitc).unwrap();
    let (d, _) = data(k, nd, 9);
    let mut ws = SparseWorkspace::default();
    let mut outs = |multi: &SparseMultiGp, jac: Option<&mut Vec<Vec<f64>>>| {
        let (mut m, mut v) = (vec![0.0; k * q], vec![0.0; k * q]);
        let (mut dm, mut dv) = (vec![0.0; k * q * nd], vec![0.0; k * q * nd]);
        let r = match jac {
            Some(j) => {
                multi.predict_conditional_into(&d, [&mut m, &mut v, &mut dm, &mut dv], j, &mut ws)
            }
            None => {
                multi.predict_with_gradients_into(&d, &mut m, &mut v, &mut dm, &mut dv, &mut ws)
            }
        };
        r.map(|_| (m, v, dm, dv))
    };
    let mut jac = Vec::new();
    assert!(matches!(
        outs(&multi, Some(&mut jac)),
        Err(Error::InvalidInput { .. })
    ));
    for o in 0..q {
        multi.gp_mut(o).unwrap().set_conditional(true);
    }
    let with = outs(&multi, Some(&mut jac)).unwrap();
    assert_eq!(with, outs(&multi, None).unwrap());
    for (o, mo) in [7usize, 5].into_iter().enumerate() {
        let mut alone = vec![0.0; k * mo];
        multi.gps()[o]
            .inducing_jacobian_into(&d, &mut alone)
            .unwrap();
        assert_eq!(jac[o].len(), k * mo);
        for (a, b) in jac[o].iter().zip(&alone) {
            assert!((a - b).abs() <= 1e-12 * (1.0 + b.abs()), "{o}: {a} vs {b}");
        }
    }
}
