//! The robots written in the expression language keep their promises on
//! every one of 100 seeds (seeds 500–599, away from the ones their
//! scenarios were built on): the double integrator never crosses the wall
//! and stops within 0.25 of it; the unicycle never enters a disc; the
//! cart-pole stays on its track and gets within 0.1 of its end; the
//! quadrotor touches neither the floor nor the hanging obstacle.

use bayes_cbf_scenario::sweep::{run_seeds, SeedRange, Shard, SweepMeta, SweepRow};

fn sweep(name: &str) -> Vec<SweepRow> {
    let meta = SweepMeta {
        scenario: name.into(),
        sets: vec![
            "outputs.plots=false".into(),
            "outputs.animation=false".into(),
        ],
        seeds: SeedRange {
            start: 500,
            end: 600,
        },
        shard: Shard { index: 0, count: 1 },
        goal_tolerance: 0.5,
    };
    run_seeds(&meta, &|_, _| {}).unwrap()
}

#[test]
fn double_integrator_stops_before_the_wall_on_every_seed() {
    let rows = sweep("double-integrator");
    assert_eq!(rows.len(), 100);
    for r in &rows {
        // h = 1 − p: never negative, and the cart gets within 0.25 of the wall
        assert!(r.safe && !r.collided, "seed {}: {r:?}", r.seed);
        assert!(
            (0.0..0.25).contains(&r.min_barrier),
            "seed {}: {r:?}",
            r.seed
        );
    }
}

#[test]
fn unicycle_never_enters_a_disc_on_any_seed() {
    let rows = sweep("unicycle-obstacles");
    assert_eq!(rows.len(), 100);
    for r in &rows {
        assert!(
            r.safe && !r.collided && r.min_barrier >= 0.0,
            "seed {}: {r:?}",
            r.seed
        );
    }
    // it also gets to the goal, except where a barrier and the CLF meet
    // head-on (the CBF-CLF deadlock, a stop in front of a disc)
    let reached = rows.iter().filter(|r| r.goal_distance < 0.5).count();
    assert!(reached >= 95, "goal reached on {reached}/100");
}

#[test]
fn cartpole_stays_on_its_track_on_every_seed() {
    let rows = sweep("cartpole-track");
    assert_eq!(rows.len(), 100);
    for r in &rows {
        // both track ends: h ≥ 0, and the cart is driven to within 0.1 of one
        assert!(r.safe && !r.collided, "seed {}: {r:?}", r.seed);
        assert!(
            (0.0..0.1).contains(&r.min_barrier),
            "seed {}: {r:?}",
            r.seed
        );
    }
}

#[test]
fn quadrotor_touches_neither_floor_nor_obstacle_on_any_seed() {
    let rows = sweep("quadrotor-floor");
    assert_eq!(rows.len(), 100);
    for r in &rows {
        assert!(
            r.safe && !r.collided && r.min_barrier >= 0.0,
            "seed {}: {r:?}",
            r.seed
        );
    }
}
