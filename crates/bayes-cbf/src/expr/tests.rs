use super::*;
use crate::autodiff::{seed_dual, seed_hyper};
use num_dual::{Dual64, HyperDual64};

fn names() -> Names {
    Names::new(&["x", "y"], &[("a", 1.5), ("b", -0.25)]).unwrap()
}

/// Each case: the text and the same function written in Rust.
type Case = (&'static str, fn(f64, f64) -> f64);

fn cases() -> Vec<Case> {
    vec![
        ("x + y*2 - 3/x", |x, y| x + y * 2.0 - 3.0 / x),
        ("-x^2", |x, _| -(x * x)),
        ("2^-1*x", |x, _| 0.5 * x),
        ("x^y", |x, y| x.powf(y)),
        ("x^2.5 + y^3", |x, y| x.powf(2.5) + y.powi(3)),
        ("(x*x + y*y)^1.5 - x^(1/3)", |x, y| {
            (x * x + y * y).powf(1.5) - x.cbrt()
        }),
        ("2^3^2", |_, _| 2f64.powi(9)),
        ("a*sin(x)*cos(y) - tan(x*y)", |x, y| {
            1.5 * x.sin() * y.cos() - (x * y).tan()
        }),
        ("asin(y/3) + acos(y/4) + atan(x)", |x, y| {
            (y / 3.0).asin() + (y / 4.0).acos() + x.atan()
        }),
        ("atan2(y, x) + atan2(x, -y)", |x, y| {
            y.atan2(x) + x.atan2(-y)
        }),
        ("sinh(x) * cosh(y) + tanh(x - y)", |x, y| {
            x.sinh() * y.cosh() + (x - y).tanh()
        }),
        ("exp(b*x) + log(x) + sqrt(x*x + y*y)", |x, y| {
            (-0.25 * x).exp() + x.ln() + (x * x + y * y).sqrt()
        }),
        ("abs(y) + min(x, y) + max(x, 2*y)", |x, y| {
            y.abs() + x.min(y) + x.max(2.0 * y)
        }),
        ("pi * (x - y) / (a + b)", |x, y| {
            std::f64::consts::PI * (x - y) / 1.25
        }),
        ("+x - -y", |x, y| x + y),
        ("((x))*((((y))))", |x, y| x * y),
        ("1.5e-1*x + 2E+1*y + .5", |x, y| 0.15 * x + 20.0 * y + 0.5),
    ]
}

/// Points away from the kinks of abs, min and max.
const POINTS: [(f64, f64); 4] = [(0.7, 0.3), (1.9, -1.2), (0.45, 2.1), (2.6, 0.8)];

#[test]
fn values_match_the_rust_functions() {
    let n = names();
    for (text, f) in cases() {
        let e = Expr::parse("e", text, &n).unwrap();
        for (x, y) in POINTS {
            let got: f64 = e.eval(&[x, y]);
            let want = f(x, y);
            assert!(
                (got - want).abs() <= 1e-14 * want.abs().max(1.0),
                "{text} at ({x}, {y}): {got} vs {want}"
            );
        }
    }
}

#[test]
fn gradients_and_hessians_match_finite_differences() {
    let n = names();
    let h = 1e-4;
    for (text, f) in cases() {
        let e = Expr::parse("e", text, &n).unwrap();
        for (x0, y0) in POINTS {
            let p = [x0, y0];
            // f at p + s_a h e_a + s_b h e_b
            let at = |a: usize, sa: f64, b: usize, sb: f64| {
                let mut w = p;
                w[a] += sa * h;
                w[b] += sb * h;
                f(w[0], w[1])
            };
            let mut d = [Dual64::from(0.0); 2];
            let mut hd = [HyperDual64::from(0.0); 2];
            for j in 0..2 {
                seed_dual(&p, j, &mut d);
                let g = e.eval(&d).eps;
                let fd = (at(j, 1.0, j, 0.0) - at(j, -1.0, j, 0.0)) / (2.0 * h);
                assert!(
                    (g - fd).abs() <= 1e-6 * fd.abs().max(1.0),
                    "∂{j} {text} at {p:?}: {g} vs {fd}"
                );
                for k in 0..2 {
                    seed_hyper(&p, j, k, &mut hd);
                    let v = e.eval(&hd).eps1eps2;
                    let fd = (at(j, 1.0, k, 1.0) - at(j, 1.0, k, -1.0) - at(j, -1.0, k, 1.0)
                        + at(j, -1.0, k, -1.0))
                        / (4.0 * h * h);
                    assert!(
                        (v - fd).abs() <= 1e-4 * fd.abs().max(1.0),
                        "∂{j}∂{k} {text} at {p:?}: {v} vs {fd}"
                    );
                }
            }
        }
    }
}

/// Value, gradient and Hessian of `e` at `p` by (hyper-)dual numbers.
fn derivatives(e: &Expr, p: [f64; 2]) -> (f64, [f64; 2], [[f64; 2]; 2]) {
    let (mut g, mut hs) = ([0.0; 2], [[0.0; 2]; 2]);
    let mut d = [Dual64::from(0.0); 2];
    let mut hd = [HyperDual64::from(0.0); 2];
    for j in 0..2 {
        seed_dual(&p, j, &mut d);
        g[j] = e.eval(&d).eps;
        for k in 0..2 {
            seed_hyper(&p, j, k, &mut hd);
            hs[j][k] = e.eval(&hd).eps1eps2;
        }
    }
    (e.eval(&p), g, hs)
}

/// A constant non-integer power at and near a zero base: `(x² + y²)^1.5`
/// is C² at the origin with value, gradient and Hessian 0 (num-dual's
/// `powf` gave NaN there, `∞ · 0`), `x^0.5` at `10⁻¹⁵⁰` has finite
/// derivatives (num-dual's overflowed), and `x^0.5` at 0, whose derivative
/// is infinite, is not finite rather than a number.
#[test]
fn constant_powers_are_exact_at_and_near_a_zero_base() {
    let n = names();
    let cone = Expr::parse("e", "9 - (x^2 + y^2)^1.5", &n).unwrap();
    assert_eq!(
        derivatives(&cone, [0.0, 0.0]),
        (9.0, [0.0; 2], [[0.0; 2]; 2])
    );
    // away from the origin: r³ with r = |(x, y)|, against its closed form
    let (x, y) = (0.3, -0.4);
    let (v, g, hs) = derivatives(&cone, [x, y]);
    let r = 0.5;
    assert!((v - (9.0 - r * r * r)).abs() < 1e-14);
    let want_g = [-3.0 * r * x, -3.0 * r * y];
    let want_h = [
        [-3.0 * (r + x * x / r), -3.0 * x * y / r],
        [-3.0 * x * y / r, -3.0 * (r + y * y / r)],
    ];
    for j in 0..2 {
        assert!((g[j] - want_g[j]).abs() < 1e-13, "{g:?}");
        for k in 0..2 {
            assert!((hs[j][k] - want_h[j][k]).abs() < 1e-13, "{hs:?}");
        }
    }
    let root = Expr::parse("e", "x^0.5 + y", &n).unwrap();
    let (v, g, hs) = derivatives(&root, [1e-150, 1.0]);
    assert_eq!(v, 1e-75 + 1.0);
    assert!((g[0] / (0.5e75) - 1.0).abs() < 1e-12, "{g:?}");
    assert!((hs[0][0] / (-0.25e225) - 1.0).abs() < 1e-12, "{hs:?}");
    let (_, g, _) = derivatives(&root, [0.0, 1.0]);
    assert!(!g[0].is_finite(), "{g:?}");
    // integer powers of small bases: num-dual's r^(n−3) r³ overflowed
    for (text, t, want) in [
        ("x^-1 + 0*y", 1e-100, [1e100, -1e200, 2e300]),
        ("x^-2 + 0*y", 1e-70, [1e140, -2e210, 6e280]),
        ("x^3 + 0*y", -2.0, [-8.0, 12.0, -12.0]),
    ] {
        let e = Expr::parse("e", text, &n).unwrap();
        let (v, g, h) = derivatives(&e, [t, 1.0]);
        for (got, w) in [v, g[0], h[0][0]].into_iter().zip(want) {
            assert!(
                (got - w).abs() <= 1e-12 * w.abs(),
                "{text} at {t:e}: {got:e} vs {w:e}"
            );
        }
    }
    // |x|^1.5 is C¹ at 0; x·|x|^0.5, the same function, is a product with
    // a factor whose derivative is infinite there, which forward
    // differentiation cannot resolve: its value is 0, its derivative not
    // finite (the caller reports that, not a NaN value)
    let mut d = [Dual64::from(0.0); 2];
    seed_dual(&[0.0, 1.0], 0, &mut d);
    let drag = Expr::parse("e", "abs(x)^1.5", &n).unwrap().eval(&d);
    assert_eq!((drag.re, drag.eps), (0.0, 0.0));
    let product = Expr::parse("e", "x*abs(x)^0.5", &n).unwrap().eval(&d);
    assert_eq!(product.re, 0.0);
    assert!(!product.eps.is_finite());
}

/// `t^e` as `sign · exp(e ln|t|)`, in logarithms so that it is finite
/// wherever the result is (0 at `t = 0` for `e > 0`).
fn power(t: f64, e: f64) -> f64 {
    if t == 0.0 {
        return if e > 0.0 { 0.0 } else { f64::INFINITY };
    }
    (e * t.abs().ln()).exp()
}

/// Never a finite wrong number: `x^c` and `(x² + y²)^c` on a grid of
/// exponents and of bases from 10⁻³²⁰ to 10⁵⁰ (subnormal squares and
/// underflowing ones included) have a value, gradient and Hessian that are
/// either their closed forms (to 1e-9 relative, or 1e-200 absolute) or not
/// finite, which the callers report as an error at that state.
#[test]
fn constant_powers_are_right_or_not_finite_at_any_scale() {
    let n = names();
    let close = |got: f64, want: f64| {
        // below 1e-200 an intermediate power can be subnormal, with fewer
        // digits than a double has: such an entry is right to its size
        !got.is_finite() || (got - want).abs() <= 1e-9 * want.abs() + 1e-200
    };
    for c in [-2.0, -1.0, -0.5, 0.5, 0.75, 1.5, 2.5, 3.0, 4.0] {
        let single = Expr::parse("e", &format!("x^({c})"), &n).unwrap();
        let radial = Expr::parse("e", &format!("(x^2 + y^2)^({c})"), &n).unwrap();
        for e10 in -320..=50 {
            for t in [1.0f64, 3.7] {
                let t = t * 10f64.powi(e10);
                if t == 0.0 {
                    continue;
                }
                let (v, g, h) = derivatives(&single, [t, 1.0]);
                let want = [
                    power(t, c),
                    c * power(t, c - 1.0),
                    c * (c - 1.0) * power(t, c - 2.0),
                ];
                for (got, w) in [v, g[0], h[0][0]].into_iter().zip(want) {
                    assert!(close(got, w), "x^{c} at {t:e}: {got:e} vs {w:e}");
                }
                // along y = 0: V = |t|^(2c), ∂x = 2c t^(2c−1), ∂xx = 2c(2c−1)
                // t^(2c−2), the sum of the chain rule's terms 2c t^(2c−2)
                // and 4c(c−1) t^(2c−2), which cancel for c = 1/2: the
                // Hessian is right to the terms' size; below 1e-154, t² is
                // subnormal, with few digits, or 0, in any f64 evaluation:
                // there the Hessian is within a tenth of the terms' size (or
                // below 1e-100) or not finite (once 10³⁰⁷ where it is 0)
                let (v, g, h) = derivatives(&radial, [t, 0.0]);
                let terms = (2.0 * c).abs() + (4.0 * c * (c - 1.0)).abs();
                if t < 1e-154 {
                    let w = 2.0 * c * (2.0 * c - 1.0) * power(t, 2.0 * c - 2.0);
                    let size = terms * power(t, 2.0 * c - 2.0);
                    let hxx = h[0][0];
                    assert!(
                        !hxx.is_finite() || (hxx - w).abs() <= 0.1 * size + 1e-100,
                        "(x²+y²)^{c} at ({t:e}, 0): ∂xx {hxx:e} vs {w:e}"
                    );
                    continue;
                }
                let want = [
                    (power(t, 2.0 * c), 0.0),
                    (2.0 * c * power(t, 2.0 * c - 1.0), 0.0),
                    (
                        2.0 * c * (2.0 * c - 1.0) * power(t, 2.0 * c - 2.0),
                        terms * power(t, 2.0 * c - 2.0),
                    ),
                ];
                for (got, (w, size)) in [v, g[0], h[0][0]].into_iter().zip(want) {
                    assert!(
                        close(got, w) || (got - w).abs() <= 1e-12 * size,
                        "(x²+y²)^{c} at ({t:e}, 0): {got:e} vs {w:e}"
                    );
                }
            }
        }
    }
}

/// `min` and `max` pass a NaN on whichever side it stands, so that a
/// function undefined at a state is reported there.
#[test]
fn min_and_max_keep_a_nan_on_either_side() {
    let n = names();
    for text in [
        "min(x, log(y))",
        "min(log(y), x)",
        "max(x, sqrt(y))",
        "max(sqrt(y), x)",
    ] {
        let e = Expr::parse("e", text, &n).unwrap();
        let v: f64 = e.eval(&[0.5, -1.0]);
        assert!(v.is_nan(), "{text}: {v}");
        let (v, _, _) = derivatives(&e, [0.5, 2.0]);
        assert!(v.is_finite(), "{text}: {v}");
    }
}

#[test]
fn parameters_and_constant_subexpressions_fold() {
    let n = Names::new(&["theta"], &[("m", 2.0), ("l", 0.5)]).unwrap();
    let e = Expr::parse("g", "1/(m*l^2)", &n).unwrap();
    assert_eq!(e.constant(), Some(2.0));
    assert_eq!(e.nodes.len(), 1);
    let e = Expr::parse("f", "-10/l*sin(theta) + 2*pi", &n).unwrap();
    assert!(e.uses(0) && e.constant().is_none());
    // -10/l and 2*pi are single constants: sin, θ, one product, one sum
    assert_eq!(e.nodes.len(), 6, "{:?}", e.nodes);
}

/// A parameter no expression uses is named: its value (or an override of
/// it) would change nothing. Used in any one expression is enough.
#[test]
fn unused_parameters_are_named() {
    let n = Names::new(&["x"], &[("k", 2.0), ("K", 3.0)]).unwrap();
    Expr::parse("f[0]", "-k*x", &n).unwrap();
    let s = n.check_params_used().unwrap_err().to_string();
    assert!(
        s.starts_with("params.K") && s.contains("no expression uses"),
        "{s}"
    );
    Expr::parse("f[1]", "K + 0*x", &n).unwrap();
    n.check_params_used().unwrap();
    // the system, barrier and CLF constructors check their own
    let e = crate::systems::ExpressionSystem::new(
        &["x"],
        &["u"],
        &[("m", 1.0), ("mass", 2.0)],
        &["0"],
        &[vec!["1/m"]],
        &[],
    )
    .unwrap_err();
    assert!(e.to_string().contains("params.mass"), "{e}");
    let e = crate::barrier::ExpressionBarrier::new(&["x"], &[("r", 1.0)], "1 - x", 1, vec![1.0])
        .unwrap_err();
    assert!(e.to_string().contains("params.r"), "{e}");
    let e =
        crate::barrier::ExpressionClf::new(&["x"], &[("w", 1.0)], "(x - x_d)^2", 1.0).unwrap_err();
    assert!(e.to_string().contains("params.w"), "{e}");
}

/// `abs`, `min` and `max` of a variable are kinks; folded into a
/// constant they are not.
#[test]
fn kinks_are_the_non_differentiable_functions_of_a_variable() {
    let n = names();
    let kinks = |t: &str| Expr::parse("h", t, &n).unwrap().kinks();
    assert_eq!(kinks("min(1 - x, 1 - y)"), vec!["min"]);
    assert_eq!(kinks("max(x, 0) + abs(y)"), vec!["abs", "max"]);
    assert!(kinks("x^2 + sin(y) + abs(a) + min(a, b)").is_empty());
    let b =
        crate::barrier::ExpressionBarrier::new(&["x", "y"], &[], "min(1 - x, 1 - y)", 1, vec![1.0])
            .unwrap();
    assert_eq!(b.kinks(), vec!["min"]);
}

#[test]
fn errors_name_the_field_and_column() {
    let mut n = names();
    n.reserve("u", "f and g are functions of the state only")
        .unwrap();
    let cases = [
        ("x + * y", "column 5", "expected a number"),
        ("sin(x", "column 6", "expected ')'"),
        ("x y", "column 3", "unexpected 'y'"),
        (
            "x + z",
            "column 5",
            "unknown name 'z' (known: x, y, a, b, pi)",
        ),
        ("foo(x)", "column 1", "unknown function 'foo'"),
        ("atan2(x)", "column 1", "atan2 takes two arguments, got 1"),
        ("sin(x, y)", "column 1", "sin takes one argument, got 2"),
        ("x + sin", "column 5", "write sin(...)"),
        ("", "column 1", "empty expression"),
        ("   ", "column 1", "empty expression"),
        ("x # y", "column 3", "unexpected character '#'"),
        (
            "2 * u",
            "column 5",
            "'u' cannot be used here: f and g are functions",
        ),
        ("1.2.3", "column 1", "malformed number '1.2.3'"),
        ("θ + 1", "column 1", "unexpected character 'θ'"),
        ("x + (y", "column 7", "expected ')', found the end"),
        ("max()", "column 1", "max takes two arguments, got 0"),
        (
            "x - 1e400*y",
            "column 5",
            "the number '1e400' is beyond the range",
        ),
    ];
    for (text, col, msg) in cases {
        let e = Expr::parse("barriers[0].h", text, &n).unwrap_err();
        let s = e.to_string();
        assert!(
            s.starts_with("barriers[0].h") && s.contains(col) && s.contains(msg),
            "{text}: {s}"
        );
    }
    // parameters folded into a constant that is not finite
    let c = Names::new(&["x"], &[("c", -1.0), ("m", 0.0)]).unwrap();
    for text in ["x + 0*log(c)", "-x/m", "x^(1/m)", "-c/m*x"] {
        let s = Expr::parse("f[1]", text, &c).unwrap_err().to_string();
        assert!(
            s.starts_with("f[1]") && s.contains("without states") && s.contains("parameters"),
            "{text}: {s}"
        );
    }
    let deep = format!("{}x{}", "(".repeat(200), ")".repeat(200));
    let s = Expr::parse("h", &deep, &n).unwrap_err().to_string();
    assert!(s.contains("nested deeper"), "{s}");
    let minus = format!("{}x", "-".repeat(500));
    assert!(Expr::parse("h", &minus, &n).is_err());
    for (vars, params, want) in [
        (vec!["x", "x"], vec![], "given twice"),
        (vec!["x"], vec![("x", 1.0)], "given twice"),
        (vec!["2x"], vec![], "not a name"),
        (vec!["sin"], vec![], "built-in"),
        (vec!["x"], vec![("pi", 3.0)], "built-in"),
        (vec!["x"], vec![("c", f64::NAN)], "params.c"),
    ] {
        let s = Names::new(&vars, &params).unwrap_err().to_string();
        assert!(s.contains(want), "{vars:?} {params:?}: {s}");
    }
}

/// A xorshift generator of the fuzz tests, from `seed`.
fn xorshift(mut seed: u64) -> impl FnMut() -> u64 {
    move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed
    }
}

#[test]
fn random_text_never_panics() {
    // a fuzz over the language's own alphabet: every outcome is a value or
    // a typed error
    let alphabet: Vec<char> = "xyab()+-*/^,. 0123456789esinqrtlogmaxpi#".chars().collect();
    let n = names();
    let mut next = xorshift(0x9E37_79B9_7F4A_7C15);
    let mut parsed = 0;
    for _ in 0..20_000 {
        let len = (next() % 24) as usize;
        let text: String = (0..len)
            .map(|_| alphabet[(next() % alphabet.len() as u64) as usize])
            .collect();
        if let Ok(e) = Expr::parse("h", &text, &n) {
            parsed += 1;
            let _: f64 = e.eval(&[0.3, -0.7]);
            let _ = e.eval(&[HyperDual64::from(0.3), HyperDual64::from(-0.7)]);
        }
    }
    assert!(parsed > 100, "{parsed}");
}

/// The node's value by a recursive walk of its operand indices: the
/// reference for the postfix stack machine of [`Expr::eval`].
fn walk<D: DualNum<Primitive = f64> + Copy>(nodes: &[Node], i: u32, x: &[D]) -> D {
    let node = nodes[i as usize];
    match (node, node.children()) {
        (Node::Const(c), _) => D::from(c),
        (Node::Var(v), _) => x[v as usize],
        (_, [Some(a), None]) => unary(node, walk(nodes, a, x)),
        (_, [Some(a), Some(b)]) => binary(node, walk(nodes, a, x), walk(nodes, b, x)),
        _ => unreachable!("operands fill from the first"),
    }
}

/// A random well-formed expression over `x`, `y`, `a`, `b` of nesting at
/// most `depth`.
fn random_expression(next: &mut impl FnMut() -> u64, depth: usize) -> String {
    let leaf = ["x", "y", "a", "b", "0.5", "2", "pi"];
    if depth == 0 || next().is_multiple_of(4) {
        return leaf[(next() % leaf.len() as u64) as usize].to_string();
    }
    let mut sub = || random_expression(next, depth - 1);
    let (p, q) = (sub(), sub());
    match next() % 9 {
        0 => format!("{p} + {q}"),
        1 => format!("{p} - ({q})"),
        2 => format!("({p}) * ({q})"),
        3 => format!("({p}) / (2 + ({q})^2)"),
        4 => format!("-({p})"),
        5 => format!("sin({p}) + cos({q})"),
        6 => format!("atan2({p}, {q})"),
        7 => format!("max({p}, {q}) - min({q}, {p})"),
        _ => format!("({p})^2 + exp(-({q})^2)"),
    }
}

#[test]
fn the_stack_machine_matches_a_recursive_walk() {
    let n = names();
    let mut next = xorshift(0xD1B5_4A32_D192_ED03);
    let mut deep = 0;
    for case in 0..400 {
        let text = random_expression(&mut next, 2 + case % 7);
        let e = Expr::parse("h", &text, &n).unwrap();
        let root = (e.nodes.len() - 1) as u32;
        for (x, y) in POINTS {
            let got: f64 = e.eval(&[x, y]);
            let want = walk(&e.nodes, root, &[x, y]);
            assert!(got.to_bits() == want.to_bits(), "{text}: {got} vs {want}");
            let hd = [
                HyperDual64::new(x, 1.0, 0.0, 0.0),
                HyperDual64::new(y, 0.0, 1.0, 0.0),
            ];
            let (got, want) = (e.eval(&hd), walk(&e.nodes, root, &hd));
            assert!(got.eps1eps2.to_bits() == want.eps1eps2.to_bits(), "{text}");
        }
        deep += usize::from(e.stack > INLINE_STACK);
    }
    // the same for expressions that hold more operands than the inline stack
    for levels in [7, 8, 9, 20, 31] {
        let text = "x + (y * (".repeat(levels) + "a" + &"))".repeat(levels);
        let e = Expr::parse("h", &text, &n).unwrap();
        deep += usize::from(e.stack > INLINE_STACK);
        let root = (e.nodes.len() - 1) as u32;
        let (got, want): (f64, f64) = (e.eval(&[0.3, 0.9]), walk(&e.nodes, root, &[0.3, 0.9]));
        assert_eq!(got.to_bits(), want.to_bits(), "{levels} levels");
    }
    assert!(deep >= 3, "{deep} expressions on the heap stack");
}

/// A sum of 200 000 terms (a chain, not a nesting: the parser accepts it)
/// evaluates with its derivatives on a thread of 128 KiB of stack, where a
/// recursive evaluation would need one frame per term.
#[test]
fn long_sums_evaluate_in_bounded_stack() {
    let terms = 200_000;
    let text = "x*x + ".repeat(terms) + "y";
    let e = Expr::parse("h", &text, &names()).unwrap();
    let (x, y) = (0.7, -0.4);
    let (v, d) = std::thread::Builder::new()
        .stack_size(128 << 10)
        .spawn(move || {
            let v: f64 = e.eval(&[x, y]);
            let d = e.eval(&[HyperDual64::new(x, 1.0, 1.0, 0.0), HyperDual64::from(y)]);
            (v, d)
        })
        .unwrap()
        .join()
        .unwrap();
    // h = t x² + y, ∂h/∂x = 2 t x, ∂²h/∂x² = 2 t
    let t = terms as f64;
    let close = |got: f64, want: f64| (got - want).abs() <= 1e-9 * want.abs();
    assert!(close(v, t * x * x + y), "{v}");
    assert!(close(d.eps1, 2.0 * t * x), "{}", d.eps1);
    assert!(close(d.eps1eps2, 2.0 * t), "{}", d.eps1eps2);
}

/// `x^y` with a variable exponent, against its closed-form derivatives:
/// `∂x = y x^(y−1)`, `∂y = x^y ln x`, `∂xx = y(y−1)x^(y−2)`,
/// `∂xy = x^(y−1)(1 + y ln x)`, `∂yy = x^y ln²x`. At a positive base every
/// entry; at a negative base with an integer exponent the value and the
/// derivatives in `x` (there is none in `y`: it is not finite); at a zero
/// base above the order, zeros.
#[test]
fn a_variable_power_has_powf_values_and_its_closed_form_derivatives() {
    let n = names();
    let e = Expr::parse("e", "x^y", &n).unwrap();
    let close = |got: f64, want: f64| (got - want).abs() <= 1e-13 * want.abs().max(1.0);
    for (x, y) in [(2.0f64, 3.0f64), (0.3, -1.7), (5.5, 0.25), (1.0, 2.0)] {
        let (v, g, hs) = derivatives(&e, [x, y]);
        let l = x.ln();
        let want_g = [y * x.powf(y - 1.0), x.powf(y) * l];
        let want_h = [
            [
                y * (y - 1.0) * x.powf(y - 2.0),
                x.powf(y - 1.0) * (1.0 + y * l),
            ],
            [x.powf(y - 1.0) * (1.0 + y * l), x.powf(y) * l * l],
        ];
        assert_eq!(v, x.powf(y), "value at ({x}, {y})");
        for j in 0..2 {
            assert!(close(g[j], want_g[j]), "∂{j} at ({x}, {y}): {}", g[j]);
            for k in 0..2 {
                assert!(close(hs[j][k], want_h[j][k]), "∂{j}∂{k} at ({x}, {y})");
            }
        }
    }
    assert_eq!(e.eval(&[2.0f64, 3.0]), 8.0);
    // a negative base with an integer exponent
    let (v, g, hs) = derivatives(&e, [-2.0, 3.0]);
    assert_eq!((v, g[0], hs[0][0]), (-8.0, 12.0, -12.0));
    assert!(!g[1].is_finite() && !hs[1][1].is_finite());
    assert!(e.eval(&[-2.0f64, 2.5]).is_nan());
    // a zero base: x^y and its derivatives tend to 0 for y > 1
    let (v, g, hs) = derivatives(&e, [0.0, 2.5]);
    assert_eq!((v, g, hs), (0.0, [0.0; 2], [[0.0; 2]; 2]));
    assert_eq!(e.eval(&[0.0f64, 0.5]), 0.0);
    // whole exponents at a zero base: x^0 = 1 and x^1 = x with their
    // derivatives in x (0 · ∞ gave NaN), none in y below the order
    assert_eq!(e.eval(&[0.0f64, 0.0]), 1.0);
    let (v, g, hs) = derivatives(&e, [0.0, 1.0]);
    assert_eq!((v, g[0], hs[0][0]), (0.0, 1.0, 0.0));
    let (v, g, _) = derivatives(&e, [0.0, 2.0]);
    assert_eq!((v, g), (0.0, [0.0, 0.0]));
    let shifted = Expr::parse("e", "(x + 1)^(y*0 + 1) - 1", &n).unwrap();
    let (v, g, hs) = derivatives(&shifted, [-1.0, 1.0]);
    assert_eq!((v, g[0], hs[0][0]), (-1.0, 1.0, 0.0));
    // ∂x = 0.5 x^−0.5 is infinite at 0, and so is ∂xy at y = 1
    assert!(!derivatives(&e, [0.0, 0.5]).1[0].is_finite());
    assert!(!derivatives(&e, [0.0, 1.0]).2[0][1].is_finite());
}
