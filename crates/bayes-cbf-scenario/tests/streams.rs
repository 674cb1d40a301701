//! What the bounded data policies keep, on the standard Ackermann stream
//! workload ([`bayes_cbf_scenario::workloads`]).

use bayes_cbf::gp::held_out_errors;
use bayes_cbf::systems::Ackermann;
use bayes_cbf_scenario::workloads::{ackermann_control, ackermann_data, ackermann_heading_sweep};

/// The trade-off on a stream whose heading sweeps once through [−π, π):
/// a window of 60 points knows only the last 0.6 rad of heading, a budget of
/// 60 keeps points over the whole sweep and predicts `F(x)u̲` almost as well
/// as all 600 points (bench row `stream_quality`).
#[test]
fn budget_remembers_what_a_window_forgets() {
    let (steps, size) = (600, 60);
    let data = ackermann_heading_sweep(steps, 12.0, 21).unwrap();
    let test = ackermann_data(300, 12.0, 22).unwrap();
    let rmse = |mode: &str| {
        let mut m = ackermann_control(0, 0).unwrap().model;
        m.set_data(
            &data.xs[..3 * size],
            &data.us[..2 * size],
            &data.xdot[..3 * size],
        )
        .unwrap();
        for j in size..steps {
            let (x, u, xd) = (
                &data.xs[3 * j..3 * j + 3],
                &data.us[2 * j..2 * j + 2],
                &data.xdot[3 * j..3 * j + 3],
            );
            if mode == "budget" {
                m.add_observation_within_budget(x, u, xd, size).unwrap();
                continue;
            }
            m.add_observation(x, u, xd).unwrap();
            if mode == "window" {
                m.remove_oldest();
            }
        }
        let e = held_out_errors(&m, &test.xs, &test.us, &Ackermann { wheelbase: 12.0 });
        e.unwrap().rmse_fu
    };
    let (window, budget, full) = (rmse("window"), rmse("budget"), rmse("full"));
    assert!(budget < window / 10.0, "budget {budget} window {window}");
    assert!(budget < 4.0 * full, "budget {budget} full {full}");
}
