//! Safety controllers: the chance-constrained CLF-CBF SOCP (paper, Prop. 2
//! and Prop. 4), typed infeasibility (Remark 2) and declared fallbacks.

mod filter;
mod socp;

pub use filter::{
    ConstraintReport, ControlOutput, ControlStatus, Fallback, InfeasibleInfo, SafetyController,
    SafetyFilter, SafetySettings,
};
pub use socp::{SocpShape, SolveStatus};
