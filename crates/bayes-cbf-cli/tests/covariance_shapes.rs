//! `bayes-cbf run covariance-shapes --quick` (paper, Fig. 1): the MVGP's
//! column covariances share one shape, the CoGP's do not.

use serde_json::Value;

mod common;

use common::{run, scratch_dir};

#[test]
fn covariance_shapes_quick() {
    let dir = scratch_dir("covariance-shapes");
    let out = dir.join("out");
    let r = run(&[
        "run",
        "covariance-shapes",
        "--quick",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(r.status.success(), "stderr: {}", r.stderr);
    let png = std::fs::read(out.join("covariance-shapes.png")).unwrap();
    assert!(png.len() > 1000 && &png[1..4] == b"PNG");
    let s: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(s["scenario"], "covariance-shapes");
    let models = s["models"].as_array().unwrap();
    let spread = |name: &str| {
        models.iter().find(|m| m["model"] == name).unwrap()["shape_spread"]
            .as_f64()
            .unwrap()
    };
    // B_k ⊗ A: every column has the shape of A
    assert!(spread("MVGP") < 1e-9, "{}", spread("MVGP"));
    // Σ k0: the blocks are free, and the fit uses that freedom
    assert!(spread("CoGP") > 1e-2, "{}", spread("CoGP"));
    for m in models {
        let cols = m["column_covariances"].as_array().unwrap();
        assert_eq!(cols.len(), 3);
        for c in cols {
            assert!(c["trace"].as_f64().unwrap() > 0.0);
        }
    }
}
