//! The loader and the stage model on `fixtures/small_model.c`: CasADi 3.8's generated code of
//! one point d = [x1, x2, u] with f = [x1 + 0.1 x2, √x2 + u], h = x1 x2 and the Jacobians
//! transposed and padded with a zero row for u, as gpmhe generates them (made by
//!
//! ```python
//! d = ca.SX.sym("d", 3); x, u = d[:2], d[2]
//! f = ca.vertcat(x[0] + 0.1 * x[1], ca.sqrt(x[1]) + u); h = x[0] * x[1]
//! jf = ca.densify(ca.vertcat(ca.jacobian(f, x).T, ca.SX(1, 2)))
//! jh = ca.densify(ca.vertcat(ca.jacobian(h, x).T, ca.SX(1, 1)))
//! cg = ca.CodeGenerator("gpmhe_model", {"with_header": False})
//! cg.add(ca.Function("gpmhe_stage", [d], [f, jf, h, jh])); cg.add(ca.Function("gpmhe_f", [d], [f]))
//! ```
//!
//! ), compiled here with the system's C compiler.

use std::path::PathBuf;
use std::process::Command;
use std::sync::{Arc, OnceLock};

use super::{CompiledLibrary, CompiledModel};
use crate::error::Error;
use crate::mhe::{StageEval, StageModel};

/// The fixture compiled once per test run (the path of its shared library).
fn library_path() -> &'static str {
    static PATH: OnceLock<String> = OnceLock::new();
    PATH.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("gpmhe-compiled-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("a temporary directory");
        let src = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("rust/src/compiled/fixtures/small_model.c");
        let out = dir.join("small_model.so");
        let cc = std::env::var("CC").unwrap_or_else(|_| "cc".into());
        let status = Command::new(&cc)
            .args(["-O2", "-fPIC", "-shared", "-o"])
            .arg(&out)
            .arg(&src)
            .arg("-lm")
            .status()
            .expect("a C compiler (cc, or $CC) to build the fixture");
        assert!(status.success(), "the fixture did not compile");
        out.to_string_lossy().into_owned()
    })
}

fn model() -> CompiledModel {
    let lib = CompiledLibrary::load(library_path(), "gpmhe_stage", "gpmhe_f", (2, 1, 1)).unwrap();
    CompiledModel::new(Arc::new(lib))
}

#[test]
fn values_and_jacobians_at_a_batch_of_points() {
    let mut m = model();
    let d = [1.0, 4.0, 0.5, -2.0, 0.25, 0.0];
    let mut ev = StageEval::default();
    m.evaluate(&d, &mut ev).unwrap();
    assert_eq!(ev.mean_x, vec![1.4, 2.5, -1.975, 0.5]);
    assert_eq!(ev.mean_y, vec![4.0, -0.5]);
    // ∂f/∂d row-major (2 × 3) per point: [1, 0.1, 0; 0, 1/(2√x2), 0]
    assert_eq!(&ev.dmean_x[..6], &[1.0, 0.1, 0.0, 0.0, 0.25, 0.0]);
    assert_eq!(&ev.dmean_x[6..], &[1.0, 0.1, 0.0, 0.0, 1.0, 0.0]);
    assert_eq!(ev.dmean_y, vec![4.0, 1.0, 0.0, 0.25, -2.0, 0.0]);
    assert!(ev
        .var_x
        .iter()
        .chain(&ev.dvar_x)
        .chain(&ev.var_y)
        .chain(&ev.dvar_y)
        .all(|&v| v == 0.0));
    let mut next = [0.0; 2];
    m.predict_state(&[1.0, 4.0], &[0.5], &mut next).unwrap();
    assert_eq!(next, [1.4, 2.5]);
}

#[test]
fn a_value_out_of_range_is_a_numerical_failure_it_remembers() {
    let mut m = model();
    let mut ev = StageEval::default();
    let err = m.evaluate(&[1.0, -1.0, 0.0], &mut ev).unwrap_err(); // √(−1) = NaN
    assert!(
        matches!(&err, Error::Numerical(msg) if msg.starts_with("f: returned NaN")),
        "{err}"
    );
    assert!(m.is_domain_error(&err));
    assert!(!m.is_domain_error(&Error::numerical("another failure")));
    let mut next = [0.0; 2];
    let err = m
        .predict_state(&[1.0, -1.0], &[0.0], &mut next)
        .unwrap_err();
    assert!(m.is_domain_error(&err));
}

#[test]
fn wrong_dimensions_names_and_files_are_refused() {
    let path = library_path();
    let refused = |r: crate::Result<CompiledLibrary>| match r {
        Err(Error::InvalidInput { arg, msg }) => assert_eq!(arg, "model", "{msg}"),
        other => panic!("expected a refusal, got {other:?}"),
    };
    let cases = [
        (path, "gpmhe_stage", "gpmhe_f", (3, 0, 1)), // other dimensions
        (path, "gpmhe_stage", "gpmhe_f", (2, 1, 2)),
        (path, "no_such_function", "gpmhe_f", (2, 1, 1)),
        (path, "gpmhe_f", "gpmhe_stage", (2, 1, 1)), // the outputs of the other function
        ("/nonexistent/model.so", "gpmhe_stage", "gpmhe_f", (2, 1, 1)),
    ];
    for (file, stage, predict, dims) in cases {
        refused(CompiledLibrary::load(file, stage, predict, dims));
    }
    let mut m = model();
    assert!(m.evaluate(&[1.0, 2.0], &mut StageEval::default()).is_err()); // not rows of 3
}

#[test]
fn estimators_on_one_library_evaluate_in_parallel_alike() {
    let shared = Arc::new(
        CompiledLibrary::load(library_path(), "gpmhe_stage", "gpmhe_f", (2, 1, 1)).unwrap(),
    );
    let results: Vec<Vec<f64>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..4)
            .map(|_| {
                let mut m = CompiledModel::new(Arc::clone(&shared));
                s.spawn(move || {
                    let mut ev = StageEval::default();
                    let d: Vec<f64> = (0..3000).map(|i| 1.0 + (i % 7) as f64).collect();
                    m.evaluate(&d, &mut ev).unwrap();
                    ev.mean_x
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    assert!(results.windows(2).all(|w| w[0] == w[1]));
}
