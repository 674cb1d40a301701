//! Expressions: formulas over named states, controls and parameters,
//! parsed once and evaluated over dual numbers, so that the gradients and
//! Hessians of user-written systems, barriers and Lyapunov functions are
//! exact (interfaces.md, "Expressions").
//!
//! Operators `+ - * / ^`, unary minus, parentheses; functions `sin cos tan
//! asin acos atan atan2 sinh cosh tanh exp log sqrt abs min max`; the
//! constant `pi`. Parameters are folded into constants when parsed, so
//! `1/(m*l^2)` costs nothing at evaluation.
//!
//! An [`Expr`] is a flat postfix program (operands before the node that
//! uses them) run on a value stack by [`Expr::eval`], generic over
//! `D: DualNum<Primitive = f64>`: one parse serves `f64`, [`num_dual::Dual64`]
//! (gradients, Jacobians) and [`num_dual::HyperDual64`] (Hessians). The
//! evaluation does not recurse, so an expression of any length evaluates in
//! bounded call-stack space (long sums included, on worker threads too), and
//! it does not allocate unless the expression holds more than 16 pending
//! operands at once (nesting that deep). A general expression crate (exmex) parses
//! into one numeric type fixed at parse time and cannot evaluate one parsed
//! expression over a generic dual number; its symbolic partial derivatives
//! would need a parse per derivative order.
//!
//! Semantics on dual numbers: `atan2` keeps finite derivatives on the axes
//! ([`crate::barrier::atan2`]) and has zero derivatives at the origin, where
//! the angle is undefined; `min`/`max` take the derivatives of the
//! chosen argument; `abs` those of `±x`; `a^b` is `powi` for a constant
//! integer `b`, `powf` for another constant, `a^b₀ · exp((b − b₀) ln a)`
//! otherwise (`b₀` the value of `b`: `x^y` at (2, 3) is 8 exactly, and at
//! a negative base with an integer exponent it is real).

mod parse;

pub use self::names::Names;

use crate::error::InputError;
use num_dual::DualNum;

/// Builds an [`InputError::Expression`].
fn error(field: &str, column: Option<usize>, message: String) -> InputError {
    InputError::Expression {
        field: field.to_string(),
        column,
        message,
    }
}

/// Functions of the language.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Func {
    Sin,
    Cos,
    Tan,
    Asin,
    Acos,
    Atan,
    Atan2,
    Sinh,
    Cosh,
    Tanh,
    Exp,
    Log,
    Sqrt,
    Abs,
    Min,
    Max,
}

impl Func {
    const NAMES: [&'static str; 16] = [
        "sin", "cos", "tan", "asin", "acos", "atan", "atan2", "sinh", "cosh", "tanh", "exp", "log",
        "sqrt", "abs", "min", "max",
    ];
    const ALL: [Func; 16] = [
        Func::Sin,
        Func::Cos,
        Func::Tan,
        Func::Asin,
        Func::Acos,
        Func::Atan,
        Func::Atan2,
        Func::Sinh,
        Func::Cosh,
        Func::Tanh,
        Func::Exp,
        Func::Log,
        Func::Sqrt,
        Func::Abs,
        Func::Min,
        Func::Max,
    ];

    fn from_name(name: &str) -> Option<Func> {
        Self::NAMES
            .iter()
            .position(|n| *n == name)
            .map(|i| Self::ALL[i])
    }

    fn arity(self) -> usize {
        match self {
            Func::Atan2 | Func::Min | Func::Max => 2,
            _ => 1,
        }
    }

    fn arity_text(self) -> &'static str {
        if self.arity() == 2 {
            "two arguments"
        } else {
            "one argument"
        }
    }
}

/// One node; operands are indices of earlier nodes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Node {
    Const(f64),
    Var(u32),
    Neg(u32),
    Add(u32, u32),
    Sub(u32, u32),
    Mul(u32, u32),
    Div(u32, u32),
    PowI(u32, i32),
    PowF(u32, f64),
    Pow(u32, u32),
    Call1(Func, u32),
    Call2(Func, u32, u32),
}

impl Node {
    fn children(&self) -> [Option<u32>; 2] {
        match *self {
            Node::Const(_) | Node::Var(_) => [None, None],
            Node::Neg(a) | Node::PowI(a, _) | Node::PowF(a, _) | Node::Call1(_, a) => {
                [Some(a), None]
            }
            Node::Add(a, b)
            | Node::Sub(a, b)
            | Node::Mul(a, b)
            | Node::Div(a, b)
            | Node::Pow(a, b)
            | Node::Call2(_, a, b) => [Some(a), Some(b)],
        }
    }
}

/// Evaluates the postfix program `nodes` (operands before the node that
/// uses them, so each node's operands are the top of the value stack),
/// variable `v` having the value `var(v)`. `stack` holds at least
/// [`stack_need`]`(nodes)` values. No recursion: an expression of any length
/// evaluates in bounded call-stack space.
fn eval_postfix<D, V>(nodes: &[Node], var: &V, stack: &mut [D]) -> D
where
    D: DualNum<Primitive = f64> + Copy,
    V: Fn(usize) -> D,
{
    let mut sp = 0;
    for node in nodes {
        let v = match *node {
            Node::Const(c) => D::from(c),
            Node::Var(v) => var(v as usize),
            Node::Neg(_) | Node::PowI(..) | Node::PowF(..) | Node::Call1(..) => {
                sp -= 1;
                unary(*node, stack[sp])
            }
            Node::Add(..)
            | Node::Sub(..)
            | Node::Mul(..)
            | Node::Div(..)
            | Node::Pow(..)
            | Node::Call2(..) => {
                sp -= 2;
                binary(*node, stack[sp], stack[sp + 1])
            }
        };
        stack[sp] = v;
        sp += 1;
    }
    stack[0]
}

/// The most values the evaluation of `nodes` holds at once.
fn stack_need(nodes: &[Node]) -> usize {
    let (mut sp, mut most) = (0usize, 0usize);
    for node in nodes {
        let pops = node.children().iter().flatten().count();
        sp = sp + 1 - pops;
        most = most.max(sp);
    }
    most
}

/// A node of one operand applied to its value `v`.
fn unary<D: DualNum<Primitive = f64> + Copy>(node: Node, v: D) -> D {
    match node {
        Node::Neg(_) => -v,
        Node::PowI(_, n) => match n {
            0 => D::from(1.0),
            1 => v,
            2 => v * v,
            _ => pow_const(v, n as f64),
        },
        Node::PowF(_, e) => pow_const(v, e),
        Node::Call1(f, _) => match f {
            Func::Sin => v.sin(),
            Func::Cos => v.cos(),
            Func::Tan => v.tan(),
            Func::Asin => v.asin(),
            Func::Acos => v.acos(),
            Func::Atan => v.atan(),
            Func::Sinh => v.sinh(),
            Func::Cosh => v.cosh(),
            Func::Tanh => v.tanh(),
            Func::Exp => v.exp(),
            Func::Log => v.ln(),
            Func::Sqrt => v.sqrt(),
            Func::Abs => {
                if v.re() < 0.0 {
                    -v
                } else {
                    v
                }
            }
            Func::Atan2 | Func::Min | Func::Max => unreachable!("binary function"),
        },
        _ => unreachable!("node of two operands or none"),
    }
}

/// `x^c` for a constant `c`, by its Taylor series at the real part `r`:
/// `Σ_k f⁽ᵏ⁾(r) dᵏ/k!` with `d = x − r` and `f⁽ᵏ⁾(r) = c(c−1)…(c−k+1)
/// r^(c−k)`, up to the order of derivatives `D` carries (`d` is nilpotent,
/// so the sum is exact). num-dual's `powf` and `powi` form `r^(c−3) r³`
/// instead, which is `∞ · 0 = NaN` at `r = 0`, even in the value, and
/// overflows at small `r` (`x^-1` at `10⁻¹⁰⁰`).
///
/// At `r = 0` exactly, where `f⁽ᵏ⁾(0)` is infinite (`k > c`), the term is
/// `dᵏ` scaled by `±MAX³` instead: exactly 0 where `dᵏ` is (a composition
/// such as `(px² + py²)^1.5` at the origin, C² with value, gradient and
/// Hessian 0), `±∞` where it is not (any non-zero entry, subnormal ones
/// included: `x^0.5` at 0, whose derivative is infinite), and the real
/// part 0 either way, whereas `dᵏ · ∞` would be NaN in every part. (Dual
/// numbers compare by their real parts only, so whether `dᵏ` is zero
/// cannot be asked.) Elsewhere an overflowing `f⁽ᵏ⁾(r)` (a base below
/// about `10⁻³⁰⁰`) makes the result not finite, which the caller reports:
/// an error at such a state, never a wrong finite number.
fn pow_const<D: DualNum<Primitive = f64> + Copy>(x: D, c: f64) -> D {
    let r = x.re();
    let d = x - D::from(r);
    let mut out = D::from(r.powf(c));
    let (mut dk, mut coef, mut fact) = (d, c, 1.0);
    for k in 1..=D::NDERIV {
        // a whole c ≥ 0 has no derivatives past order c: 0, not 0 · ∞ at r = 0
        let f = if coef == 0.0 {
            0.0
        } else {
            coef * r.powf(c - k as f64) / fact
        };
        out += if f.is_infinite() && r == 0.0 {
            dk * f64::MAX * f64::MAX * (f64::MAX * f.signum())
        } else {
            dk * f
        };
        coef *= c - k as f64;
        fact *= (k + 1) as f64;
        dk *= d;
    }
    out
}

/// `x^y` with a variable exponent, as `x^y₀ · exp((y − y₀) ln x)` with
/// `y₀` the real part of `y`: the value is `powf`'s (`2^3 = 8` exactly,
/// where `exp(3 ln 2)` is `7.999999999999998`) and the derivatives in `x`
/// are [`pow_const`]'s, so a negative base with an integer exponent and a
/// zero base are evaluated. The derivatives in `y` carry `ln x`:
/// - `x > 0`: the identity holds to every order;
/// - `x = 0` and `y₀ > NDERIV − 1`: every derivative with a `y` in it,
///   `x^(y−j) lnᵐx` with `j < NDERIV`, tends to 0; the factor is dropped;
/// - otherwise (`x < 0`, where `x^y` is real on the integers only, or
///   `x = 0` at a lower exponent, where the limit is infinite) there is
///   no derivative in `y`: a non-zero part of `y − y₀` is scaled by
///   `MAX³` to `±∞`, which the caller reports as not finite, and its zero
///   parts stay 0, as in [`pow_const`].
fn pow_var<D: DualNum<Primitive = f64> + Copy>(x: D, y: D) -> D {
    let (r, y0) = (x.re(), y.re());
    let base = pow_const(x, y0);
    let dy = y - D::from(y0);
    if r > 0.0 {
        base * (dy * x.ln()).exp()
    } else if r == 0.0 && y0 > (D::NDERIV as f64 - 1.0).max(0.0) {
        base
    } else {
        base * (D::from(1.0) + dy * f64::MAX * f64::MAX * f64::MAX)
    }
}

/// A node of two operands applied to their values `u`, `v`.
fn binary<D: DualNum<Primitive = f64> + Copy>(node: Node, u: D, v: D) -> D {
    match node {
        Node::Add(..) => u + v,
        Node::Sub(..) => u - v,
        Node::Mul(..) => u * v,
        Node::Div(..) => u / v,
        Node::Pow(..) => pow_var(u, v),
        Node::Call2(f, ..) => match f {
            // at the origin, where the angle is undefined: atan2(±0, ±0)
            // with zero derivatives, so that a bearing term (a CLF
            // at its reference point) stays finite
            Func::Atan2 if u.re() == 0.0 && v.re() == 0.0 => D::from(u.re().atan2(v.re())),
            Func::Atan2 => crate::barrier::atan2(u, v),
            // a NaN in either argument is the result (it is reported as
            // not finite), whichever argument it is
            Func::Min => {
                if v.re() < u.re() || v.re().is_nan() {
                    v
                } else {
                    u
                }
            }
            Func::Max => {
                if v.re() > u.re() || v.re().is_nan() {
                    v
                } else {
                    u
                }
            }
            _ => unreachable!("unary function"),
        },
        _ => unreachable!("node of one operand or none"),
    }
}

/// Values an evaluation keeps on the caller's stack; an expression that
/// needs more (only one nested deeper than this) uses the heap.
const INLINE_STACK: usize = 16;

/// A parsed expression.
///
/// ```
/// use bayes_cbf::expr::{Expr, Names};
/// use num_dual::Dual64;
/// let names = Names::new(&["theta", "omega"], &[("g", 10.0), ("l", 2.0)]).unwrap();
/// let e = Expr::parse("f[1]", "-g/l*sin(theta)", &names).unwrap();
/// let d = e.eval(&[Dual64::new(0.5, 1.0), Dual64::from(0.0)]);
/// assert!((d.re + 5.0 * 0.5f64.sin()).abs() < 1e-15);
/// assert!((d.eps + 5.0 * 0.5f64.cos()).abs() < 1e-15); // ∂/∂θ, exact
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct Expr {
    nodes: Vec<Node>,
    /// [`stack_need`] of `nodes`.
    stack: usize,
    text: String,
}

impl Expr {
    /// Parses `text` over `names`; `field` names the expression in errors
    /// (`f[1]`, `barriers[0].h`). A syntax error gives its column; an unknown
    /// name lists the known ones.
    pub fn parse(field: &str, text: &str, names: &Names) -> Result<Self, InputError> {
        let mut p = parse::Parser::new(field, text, names)?;
        p.parse()?;
        // parameters and numbers folded into a constant that is not finite
        // (1/m with m = 0, log of a negative parameter) would fail at every
        // state, as if the state were the cause
        for node in &p.nodes {
            if let Node::Div(_, d) = *node {
                if p.nodes[d as usize] == Node::Const(0.0) {
                    return Err(error(
                        field,
                        None,
                        "a division by a part without states that is 0, whatever the state: check the parameters and numbers it uses".into(),
                    ));
                }
            }
            if let Node::Const(v) | Node::PowF(_, v) = *node {
                if !v.is_finite() {
                    return Err(error(
                        field,
                        None,
                        format!("a part of the expression without states is {v}, whatever the state: check the parameters and numbers it uses (a division by zero, the log of a negative number, ...)"),
                    ));
                }
            }
        }
        Ok(Self {
            stack: stack_need(&p.nodes),
            nodes: p.nodes,
            text: text.to_string(),
        })
    }

    /// The value with variable `v` equal to `var(v)`.
    fn run<D, V>(&self, var: &V) -> D
    where
        D: DualNum<Primitive = f64> + Copy,
        V: Fn(usize) -> D,
    {
        if self.stack <= INLINE_STACK {
            let mut stack = [D::from(0.0); INLINE_STACK];
            eval_postfix(&self.nodes, var, &mut stack)
        } else {
            let mut stack = vec![D::from(0.0); self.stack];
            eval_postfix(&self.nodes, var, &mut stack)
        }
    }

    /// The value at the variables `x` (in the order of [`Names::vars`]).
    ///
    /// `x` must hold at least [`Names::len`] values.
    pub fn eval<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D]) -> D {
        self.run(&|v| x[v])
    }

    /// The value when the variables are `x` followed by `y` (a Lyapunov
    /// function of the state and its reference), without concatenating.
    pub fn eval2<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], y: &[D]) -> D {
        let n = x.len();
        let var = |v: usize| if v < n { x[v] } else { y[v - n] };
        self.run(&var)
    }

    /// The constant value, if the expression does not depend on any
    /// variable.
    pub fn constant(&self) -> Option<f64> {
        match self.nodes[..] {
            [Node::Const(c)] => Some(c),
            _ => None,
        }
    }

    /// Whether variable `v` appears in the expression.
    pub fn uses(&self, v: usize) -> bool {
        self.nodes.contains(&Node::Var(v as u32))
    }

    /// The text it was parsed from.
    pub fn text(&self) -> &str {
        &self.text
    }

    /// The functions with kinks it applies to a variable (`abs`, `min`,
    /// `max`, in that order, each once): there the expression has no
    /// derivative, and automatic differentiation takes one side's.
    pub fn kinks(&self) -> Vec<&'static str> {
        [Func::Abs, Func::Min, Func::Max]
            .into_iter()
            .filter(|f| {
                self.nodes.iter().any(|node| match *node {
                    Node::Call1(g, _) | Node::Call2(g, _, _) => g == *f,
                    _ => false,
                })
            })
            .map(|f| Func::NAMES[Func::ALL.iter().position(|g| *g == f).unwrap_or(0)])
            .collect()
    }
}

/// The first failed evaluation of a function whose evaluation traits are
/// infallible (an expression, a callback), kept per thread: a non-finite
/// value or an error is recorded, and the caller asks with `take`, which
/// reports to each thread its own failure (a function shared by threads
/// does not hand one thread's failure to another). One atomic load per
/// check when nothing failed.
#[derive(Debug, Default)]
pub(crate) struct Failure {
    /// How many threads have a failure kept.
    pending: std::sync::atomic::AtomicUsize,
    messages: std::sync::Mutex<Vec<(std::thread::ThreadId, String)>>,
}

impl Failure {
    /// Keeps `message()` for this thread unless it has a failure kept.
    pub(crate) fn record(&self, message: impl FnOnce() -> String) {
        use std::sync::atomic::Ordering;
        let id = std::thread::current().id();
        let mut kept = self.messages.lock().unwrap_or_else(|e| e.into_inner());
        if !kept.iter().any(|(t, _)| *t == id) {
            kept.push((id, message()));
            self.pending.store(kept.len(), Ordering::Release);
        }
    }

    /// This thread's kept failure, clearing it.
    pub(crate) fn take(&self) -> Option<String> {
        use std::sync::atomic::Ordering;
        if self.pending.load(Ordering::Acquire) == 0 {
            return None;
        }
        let id = std::thread::current().id();
        let mut kept = self.messages.lock().unwrap_or_else(|e| e.into_inner());
        let i = kept.iter().position(|(t, _)| *t == id)?;
        let (_, message) = kept.swap_remove(i);
        self.pending.store(kept.len(), Ordering::Release);
        Some(message)
    }
}

/// Real parts of `x`, for messages.
pub(crate) fn real_parts<D: DualNum<Primitive = f64> + Copy>(x: &[D]) -> Vec<f64> {
    x.iter().map(|v| v.re()).collect()
}

mod names {
    use super::{error, Func, Node};
    use crate::error::InputError;
    use std::cell::Cell;

    /// The names an expression may use: variables (in evaluation order),
    /// parameters (folded into constants) and names reserved with a reason
    /// (a control inside `f`).
    #[derive(Debug, Clone, Default, PartialEq)]
    pub struct Names {
        vars: Vec<String>,
        params: Vec<(String, f64)>,
        /// Whether an expression parsed over these names used each
        /// parameter (parallel to `params`).
        used: Vec<Cell<bool>>,
        reserved: Vec<(String, String)>,
    }

    /// Checks that `name` can be a variable or parameter name.
    fn check_name(kind: &str, name: &str) -> Result<(), InputError> {
        let mut chars = name.chars();
        let valid = matches!(chars.next(), Some(c) if c.is_ascii_alphabetic() || c == '_')
            && chars.all(|c| c.is_ascii_alphanumeric() || c == '_');
        if !valid {
            return Err(error(
                kind,
                None,
                format!(
                    "'{name}' is not a name (letters, digits and '_', not starting with a digit)"
                ),
            ));
        }
        if name == "pi" || Func::from_name(name).is_some() {
            return Err(error(
                kind,
                None,
                format!("'{name}' is a built-in name of the expression language"),
            ));
        }
        Ok(())
    }

    impl Names {
        /// Variables `vars` and parameters `params` (name, value); names
        /// must be distinct identifiers and values finite.
        pub fn new(vars: &[&str], params: &[(&str, f64)]) -> Result<Self, InputError> {
            let mut names = Self::default();
            for v in vars {
                names.add_var(v)?;
            }
            for (p, value) in params {
                names.add_param(p, *value)?;
            }
            Ok(names)
        }

        /// The variables `state`, at least one.
        pub fn states<S: AsRef<str>>(state: &[S]) -> Result<Self, InputError> {
            if state.is_empty() {
                return Err(InputError::invalid(
                    "state",
                    0.0,
                    "at least one state is needed",
                ));
            }
            let mut names = Self::default();
            for s in state {
                names.add_var(s.as_ref())?;
            }
            Ok(names)
        }

        fn taken(&self, name: &str) -> bool {
            self.vars.iter().any(|v| v == name)
                || self.params.iter().any(|(p, _)| p == name)
                || self.reserved.iter().any(|(r, _)| r == name)
        }

        /// Checks that `name` (of `field`) is a name and not yet taken;
        /// `why` follows the error that it is.
        fn check_new(&self, field: &str, name: &str, why: &str) -> Result<(), InputError> {
            check_name(field, name)?;
            if self.taken(name) {
                let message = format!("the name '{name}' is given twice{why}");
                return Err(error(field, None, message));
            }
            Ok(())
        }

        /// Adds a variable (its index is the current [`len`](Self::len)).
        pub fn add_var(&mut self, name: &str) -> Result<(), InputError> {
            self.check_new("state", name, "")?;
            self.vars.push(name.to_string());
            Ok(())
        }

        /// Adds a parameter.
        pub fn add_param(&mut self, name: &str, value: f64) -> Result<(), InputError> {
            let why = " (a parameter cannot shadow a state or control)";
            self.check_new("params", name, why)?;
            if !value.is_finite() {
                return Err(InputError::invalid(
                    &format!("params.{name}"),
                    value,
                    "must be finite",
                ));
            }
            self.params.push((name.to_string(), value));
            self.used.push(Cell::new(false));
            Ok(())
        }

        /// Checks that every parameter was used by an expression parsed
        /// over these names (call it after the last one): an unused one
        /// is most often a misspelt name, whose value (or `--set`
        /// override) would otherwise change nothing.
        pub fn check_params_used(&self) -> Result<(), InputError> {
            match self.params.iter().zip(&self.used).find(|(_, u)| !u.get()) {
                None => Ok(()),
                Some(((name, _), _)) => Err(error(
                    &format!("params.{name}"),
                    None,
                    "no expression uses this parameter (a misspelt name? names are case-sensitive): remove it or use it".to_string(),
                )),
            }
        }

        /// Reserves `name`: using it is an error that gives `reason`.
        pub fn reserve(&mut self, name: &str, reason: &str) -> Result<(), InputError> {
            check_name("control", name)?;
            if self.taken(name) {
                return Err(error(
                    "control",
                    None,
                    format!("the name '{name}' is given twice"),
                ));
            }
            self.reserved.push((name.to_string(), reason.to_string()));
            Ok(())
        }

        /// The variable names, in evaluation order.
        pub fn vars(&self) -> &[String] {
            &self.vars
        }

        /// The number of variables.
        pub fn len(&self) -> usize {
            self.vars.len()
        }

        /// Whether there are no variables.
        pub fn is_empty(&self) -> bool {
            self.vars.is_empty()
        }

        /// The node of `name`, or why it cannot be used.
        pub(super) fn resolve(&self, name: &str) -> Result<Node, String> {
            if let Some(i) = self.vars.iter().position(|v| v == name) {
                return Ok(Node::Var(i as u32));
            }
            if let Some(i) = self.params.iter().position(|(p, _)| p == name) {
                self.used[i].set(true);
                return Ok(Node::Const(self.params[i].1));
            }
            if name == "pi" {
                return Ok(Node::Const(std::f64::consts::PI));
            }
            if let Some((_, why)) = self.reserved.iter().find(|(r, _)| r == name) {
                return Err(format!("'{name}' cannot be used here: {why}"));
            }
            let mut known: Vec<&str> = self.vars.iter().map(String::as_str).collect();
            known.extend(self.params.iter().map(|(p, _)| p.as_str()));
            known.push("pi");
            Err(format!(
                "unknown name '{name}' (known: {})",
                known.join(", ")
            ))
        }
    }
}

#[cfg(test)]
mod tests;
