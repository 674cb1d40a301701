//! Safety controllers: the chance-constrained CLF-CBF SOCP (paper, Prop. 2
//! and Prop. 4), typed infeasibility (Remark 2) and declared fallbacks.

mod dense_cone;
mod filter;
mod recalibration;
mod self_trigger;
mod socp;

pub use filter::{
    ConstraintReport, ControlOutput, ControlStatus, Fallback, InfeasibleInfo, KktData,
    SafetyController, SafetyFilter, SafetySettings,
};
pub use recalibration::{RecalibrationSettings, Recalibrator};
pub use self_trigger::{
    barrier_gradient_and_hessian_bounds, barrier_gradient_bound, evaluate_trigger, tau_in_cuboid,
    tau_relative_degree_one, tau_relative_degree_r, velocity_bound, zeta_for_tau, SelfTriggered,
    ShiftedBarrier, TauSource, TriggerReport, TriggerSettings,
};
pub use socp::{SocpShape, SolveStatus};
