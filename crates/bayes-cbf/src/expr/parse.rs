//! Tokeniser and recursive-descent parser of the expression language.
//!
//! Grammar (usual precedence; `^` binds tighter than unary minus and is
//! right-associative, so `-x^2 = -(x²)` and `2^-1 = 0.5`):
//!
//! ```text
//! sum     := product (('+' | '-') product)*
//! product := unary (('*' | '/') unary)*
//! unary   := ('-' | '+') unary | power
//! power   := primary ('^' unary)?
//! primary := number | name | name '(' sum (',' sum)* ')' | '(' sum ')'
//! ```

use super::{Func, Names, Node};
use crate::error::InputError;

/// Deepest nesting accepted: bounds the recursion of parsing (evaluation
/// does not recurse).
const MAX_DEPTH: usize = 64;

#[derive(Debug, Clone, Copy, PartialEq)]
enum Tok<'a> {
    Num(f64),
    Name(&'a str),
    Op(char),
    End,
}

/// The constructor of a binary operator's node from its operands.
type BinaryNode = fn(u32, u32) -> Node;

/// A token with its 1-based column (in characters).
struct Token<'a> {
    tok: Tok<'a>,
    col: usize,
}

pub(super) struct Parser<'a> {
    field: &'a str,
    toks: Vec<Token<'a>>,
    pos: usize,
    depth: usize,
    names: &'a Names,
    pub(super) nodes: Vec<Node>,
}

fn tokenise<'a>(field: &str, text: &'a str) -> Result<Vec<Token<'a>>, InputError> {
    let mut toks = Vec::new();
    let mut it = text.char_indices().enumerate().peekable();
    while let Some((ci, (bi, c))) = it.next() {
        let col = ci + 1;
        if c.is_whitespace() {
            continue;
        }
        if c.is_ascii_digit() || c == '.' {
            let mut end = bi + c.len_utf8();
            let mut prev = c;
            while let Some(&(_, (b2, c2))) = it.peek() {
                let exp_sign = (c2 == '+' || c2 == '-') && (prev == 'e' || prev == 'E');
                if c2.is_ascii_digit() || c2 == '.' || c2 == 'e' || c2 == 'E' || exp_sign {
                    end = b2 + c2.len_utf8();
                    prev = c2;
                    it.next();
                } else {
                    break;
                }
            }
            let lit = &text[bi..end];
            let v: f64 = lit
                .parse()
                .map_err(|_| super::error(field, Some(col), format!("malformed number '{lit}'")))?;
            if !v.is_finite() {
                return Err(super::error(
                    field,
                    Some(col),
                    format!(
                        "the number '{lit}' is beyond the range of double precision (±1.8e308)"
                    ),
                ));
            }
            toks.push(Token {
                tok: Tok::Num(v),
                col,
            });
        } else if c.is_ascii_alphabetic() || c == '_' {
            let mut end = bi + 1;
            while let Some(&(_, (b2, c2))) = it.peek() {
                if c2.is_ascii_alphanumeric() || c2 == '_' {
                    end = b2 + 1;
                    it.next();
                } else {
                    break;
                }
            }
            toks.push(Token {
                tok: Tok::Name(&text[bi..end]),
                col,
            });
        } else if "+-*/^(),".contains(c) {
            toks.push(Token {
                tok: Tok::Op(c),
                col,
            });
        } else {
            return Err(super::error(
                field,
                Some(col),
                format!("unexpected character '{c}'"),
            ));
        }
    }
    toks.push(Token {
        tok: Tok::End,
        col: text.chars().count() + 1,
    });
    Ok(toks)
}

impl<'a> Parser<'a> {
    pub(super) fn new(field: &'a str, text: &'a str, names: &'a Names) -> Result<Self, InputError> {
        Ok(Self {
            field,
            toks: tokenise(field, text)?,
            pos: 0,
            depth: 0,
            names,
            nodes: Vec::new(),
        })
    }

    fn err(&self, col: usize, msg: impl Into<String>) -> InputError {
        super::error(self.field, Some(col), msg.into())
    }

    fn peek(&self) -> &Token<'a> {
        &self.toks[self.pos]
    }

    fn next(&mut self) -> &Token<'a> {
        let t = &self.toks[self.pos];
        if !matches!(t.tok, Tok::End) {
            self.pos += 1;
        }
        t
    }

    fn expect(&mut self, op: char) -> Result<(), InputError> {
        let t = self.peek();
        if t.tok == Tok::Op(op) {
            self.pos += 1;
            Ok(())
        } else {
            let col = t.col;
            let found = describe(&t.tok);
            Err(self.err(col, format!("expected '{op}', found {found}")))
        }
    }

    /// Parses the whole text; the root is the last node.
    pub(super) fn parse(&mut self) -> Result<(), InputError> {
        if matches!(self.peek().tok, Tok::End) {
            return Err(self.err(1, "empty expression"));
        }
        self.sum()?;
        let t = self.peek();
        if !matches!(t.tok, Tok::End) {
            let (col, found) = (t.col, describe(&t.tok));
            return Err(self.err(
                col,
                format!("unexpected {found} after a complete expression"),
            ));
        }
        Ok(())
    }

    fn enter(&mut self, col: usize) -> Result<(), InputError> {
        self.depth += 1;
        if self.depth > MAX_DEPTH {
            return Err(self.err(col, format!("nested deeper than {MAX_DEPTH} levels")));
        }
        Ok(())
    }

    fn sum(&mut self) -> Result<u32, InputError> {
        let col = self.peek().col;
        self.enter(col)?;
        let a = self.left_assoc(Self::product, |op| match op {
            '+' => Some(Node::Add),
            '-' => Some(Node::Sub),
            _ => None,
        })?;
        self.depth -= 1;
        Ok(a)
    }

    fn product(&mut self) -> Result<u32, InputError> {
        self.left_assoc(Self::unary, |op| match op {
            '*' => Some(Node::Mul),
            '/' => Some(Node::Div),
            _ => None,
        })
    }

    /// `operand (op operand)*`, left-associative, for the operators that
    /// `node` gives a node for.
    fn left_assoc(
        &mut self,
        operand: fn(&mut Self) -> Result<u32, InputError>,
        node: fn(char) -> Option<BinaryNode>,
    ) -> Result<u32, InputError> {
        let mut a = operand(self)?;
        while let Tok::Op(op) = self.peek().tok {
            let Some(make) = node(op) else { break };
            self.pos += 1;
            let b = operand(self)?;
            a = self.push(make(a, b));
        }
        Ok(a)
    }

    fn unary(&mut self) -> Result<u32, InputError> {
        let col = self.peek().col;
        match self.peek().tok {
            Tok::Op('-') => {
                self.pos += 1;
                self.enter(col)?;
                let a = self.unary()?;
                self.depth -= 1;
                Ok(self.push(Node::Neg(a)))
            }
            Tok::Op('+') => {
                self.pos += 1;
                self.enter(col)?;
                let a = self.unary();
                self.depth -= 1;
                a
            }
            _ => self.power(),
        }
    }

    fn power(&mut self) -> Result<u32, InputError> {
        let base = self.primary()?;
        if self.peek().tok == Tok::Op('^') {
            let col = self.peek().col;
            self.pos += 1;
            self.enter(col)?;
            let exp = self.unary()?;
            self.depth -= 1;
            return Ok(self.power_node(base, exp));
        }
        Ok(base)
    }

    /// `a^b`: `powi` for a constant integer exponent, `powf` for another
    /// constant, a variable power otherwise.
    fn power_node(&mut self, base: u32, exp: u32) -> u32 {
        match self.nodes[exp as usize] {
            Node::Const(e) if e == e.trunc() && e.abs() <= i32::MAX as f64 => {
                self.nodes.pop();
                self.push(Node::PowI(base, e as i32))
            }
            Node::Const(e) => {
                self.nodes.pop();
                self.push(Node::PowF(base, e))
            }
            _ => self.push(Node::Pow(base, exp)),
        }
    }

    fn primary(&mut self) -> Result<u32, InputError> {
        let t = self.next();
        let (tok, col) = (t.tok, t.col);
        match tok {
            Tok::Num(v) => Ok(self.push(Node::Const(v))),
            Tok::Op('(') => {
                let a = self.sum()?;
                self.expect(')')?;
                Ok(a)
            }
            Tok::Name(name) => {
                if self.peek().tok == Tok::Op('(') {
                    self.pos += 1;
                    return self.call(name, col);
                }
                if let Some(func) = Func::from_name(name) {
                    return Err(self.err(
                        col,
                        format!(
                            "'{name}' is a function of {}: write {name}(...)",
                            func.arity_text()
                        ),
                    ));
                }
                self.names
                    .resolve(name)
                    .map(|n| self.push(n))
                    .map_err(|m| self.err(col, m))
            }
            other => Err(self.err(
                col,
                format!(
                    "expected a number, a name or '(', found {}",
                    describe(&other)
                ),
            )),
        }
    }

    fn call(&mut self, name: &str, col: usize) -> Result<u32, InputError> {
        let func = Func::from_name(name).ok_or_else(|| {
            self.err(
                col,
                format!(
                    "unknown function '{name}' (functions: {})",
                    Func::NAMES.join(" ")
                ),
            )
        })?;
        let mut args = Vec::with_capacity(2);
        if self.peek().tok != Tok::Op(')') {
            args.push(self.sum()?);
            while self.peek().tok == Tok::Op(',') {
                self.pos += 1;
                args.push(self.sum()?);
            }
        }
        self.expect(')')?;
        if args.len() != func.arity() {
            return Err(self.err(
                col,
                format!("{name} takes {}, got {}", func.arity_text(), args.len()),
            ));
        }
        Ok(match args[..] {
            [a] => self.push(Node::Call1(func, a)),
            [a, b] => self.push(Node::Call2(func, a, b)),
            _ => unreachable!("arity is 1 or 2"),
        })
    }

    /// Appends `node`, folding it to a constant when its operands are
    /// constants (they are then the last nodes, which it replaces).
    fn push(&mut self, node: Node) -> u32 {
        let kids = node.children();
        let constant = kids
            .iter()
            .flatten()
            .all(|&k| matches!(self.nodes[k as usize], Node::Const(_)));
        let has_kids = kids.iter().any(Option::is_some);
        self.nodes.push(node);
        if has_kids && constant {
            let root = (self.nodes.len() - 1) as u32;
            let first = kids.iter().flatten().min().copied().unwrap_or(root);
            // the operands and the node: a postfix program of its own
            let mut stack = [0.0; 2];
            let v = super::eval_postfix(&self.nodes[first as usize..], &|_| f64::NAN, &mut stack);
            self.nodes.truncate(first as usize);
            self.nodes.push(Node::Const(v));
        }
        (self.nodes.len() - 1) as u32
    }
}

fn describe(t: &Tok) -> String {
    match t {
        Tok::Num(v) => format!("the number {v}"),
        Tok::Name(n) => format!("'{n}'"),
        Tok::Op(c) => format!("'{c}'"),
        Tok::End => "the end of the expression".into(),
    }
}
