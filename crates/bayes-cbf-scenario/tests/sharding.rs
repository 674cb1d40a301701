//! Sharded and merged runs equal the unsharded run: calibration and seed
//! sweeps, through their text forms (part.json, sweep.csv), and bad shard
//! sets are errors.

use bayes_cbf::control::Fallback;
use bayes_cbf_scenario::experiments::calibration::{self, CalibrationPart, Options};
use bayes_cbf_scenario::experiments::ExperimentArgs;
use bayes_cbf_scenario::sweep::{
    merge_sweeps, parse_rows_csv, rows_csv, run_seeds, summarise, Shard, SweepMeta, SweepRow,
};

fn without_timing(mut v: serde_json::Value) -> serde_json::Value {
    let o = v.as_object_mut().unwrap();
    o.remove("wall_seconds");
    o.remove("threads");
    o.remove("timing");
    v
}

#[test]
fn calibration_shards_merge_into_the_unsharded_run() {
    let args = ExperimentArgs {
        seed: 11,
        quick: true,
    };
    let one = Options {
        episodes: Some(1),
        fallback: None,
    };
    let whole = calibration::run(&args, &one, &|_: usize, _: usize| {}).unwrap();
    let parts: Vec<CalibrationPart> = [2, 0, 1]
        .iter()
        .map(|&i| {
            let p = calibration::run_shard(
                &args,
                &one,
                Shard { index: i, count: 3 },
                &|_: usize, _: usize| {},
            )
            .unwrap();
            // through the file format
            serde_json::from_str(&serde_json::to_string(&p).unwrap()).unwrap()
        })
        .collect();
    let merged = calibration::merge(parts.clone()).unwrap();
    let (mut merged_summary, mut whole_summary) = (merged.summary.clone(), whole.summary.clone());
    for s in [&mut merged_summary, &mut whole_summary] {
        (s.wall_seconds, s.threads) = (0.0, 0);
    }
    assert_eq!(merged_summary, whole_summary);
    assert_eq!(merged.tables[0].csv, whole.tables[0].csv);
    assert_eq!(merged.console_table, whole.console_table);

    // missing, duplicated and foreign shards
    let e = calibration::merge(parts[..2].to_vec())
        .unwrap_err()
        .to_string();
    assert!(e.contains("missing shard(s) 1/3"), "{e}");
    let e = calibration::merge(vec![parts[0].clone(), parts[0].clone(), parts[1].clone()])
        .unwrap_err()
        .to_string();
    assert!(e.contains("given twice"), "{e}");
    let other = calibration::run_shard(
        &ExperimentArgs {
            seed: 12,
            quick: true,
        },
        &one,
        Shard { index: 1, count: 3 },
        &|_: usize, _: usize| {},
    )
    .unwrap();
    let e = calibration::merge(vec![parts[0].clone(), parts[1].clone(), other])
        .unwrap_err()
        .to_string();
    assert!(e.contains("another run"), "{e}");
    // a shard of the same run with another fallback than the default
    let max_margin = Options {
        fallback: Some(Fallback::MaxMargin),
        ..one
    };
    let other = calibration::run_shard(
        &args,
        &max_margin,
        Shard { index: 1, count: 3 },
        &|_: usize, _: usize| {},
    )
    .unwrap();
    assert_eq!(parts[0].fallback, Fallback::Relax);
    assert_eq!(other.fallback, Fallback::MaxMargin);
    // part.json names it as the command line does
    let text = serde_json::to_value(&other).unwrap();
    assert_eq!(text["fallback"], "max_margin");
    for f in [
        Fallback::MaxMargin,
        Fallback::Brake,
        Fallback::Hold,
        Fallback::Relax,
    ] {
        assert_eq!(serde_json::to_value(f).unwrap(), f.name());
    }
    let e = calibration::merge(vec![parts[0].clone(), other, parts[2].clone()])
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("fallback relax") && e.contains("fallback max_margin"),
        "{e}"
    );
    // a shard file from before the option: max-margin
    let mut v = serde_json::to_value(&parts[0]).unwrap();
    v.as_object_mut().unwrap().remove("fallback");
    let old: CalibrationPart = serde_json::from_value(v).unwrap();
    assert_eq!(old.fallback, Fallback::MaxMargin);
    // counts that contradict each other (more violations than steps, a sum
    // that is not finite) are refused, naming the field
    for (field, value, want) in [
        (
            "steps_h_violated",
            serde_json::json!(1_000_000),
            "steps_h_violated = 1000000 exceeds steps",
        ),
        (
            "solved_steps",
            serde_json::json!(1_000_000),
            "solved_steps + infeasible_steps",
        ),
        (
            "cbc_violations",
            serde_json::json!(1_000_000),
            "cbc_violations = 1000000 exceeds solved_steps",
        ),
    ] {
        let mut v = serde_json::to_value(&parts[0]).unwrap();
        v["results"][0][1][field] = value;
        let bad: CalibrationPart = serde_json::from_value(v).unwrap();
        let e = bad.check().unwrap_err().to_string();
        assert!(
            e.contains(want) && e.contains("shard 2/3, episode"),
            "{field}: {e}"
        );
        let e = calibration::merge(vec![bad, parts[1].clone(), parts[2].clone()])
            .unwrap_err()
            .to_string();
        assert!(e.contains(want), "{field}: {e}");
    }
    let mut v = serde_json::to_value(&parts[0]).unwrap();
    v["results"][0][1]["z"][0]["sum"] = "NaN".into();
    let bad: CalibrationPart = serde_json::from_value(v).unwrap();
    let e = bad.check().unwrap_err().to_string();
    assert!(e.contains("z[0]: sum = NaN"), "{e}");
    for p in &parts {
        p.check().unwrap();
    }
    assert!(calibration::merge(vec![]).is_err());
}

/// A shard: its description and its rows.
type Part = (SweepMeta, Vec<SweepRow>);

fn meta(shard: Shard) -> SweepMeta {
    let sets = ["steps=40".to_string()];
    SweepMeta::new("pendulum-safe", &sets, "3..8".parse().unwrap(), shard, 1.0).unwrap()
}

fn strip(rows: &[SweepRow]) -> Vec<(u64, bool, bool, u64, usize)> {
    rows.iter()
        .map(|r| {
            (
                r.seed,
                r.safe,
                r.collided,
                r.min_barrier.to_bits(),
                r.infeasible_steps,
            )
        })
        .collect()
}

#[test]
fn sweep_shards_merge_into_the_unsharded_sweep() {
    let whole_meta = meta(Shard::WHOLE);
    let whole = run_seeds(&whole_meta, &|_, _| {}).unwrap();
    assert_eq!(
        whole.iter().map(|r| r.seed).collect::<Vec<_>>(),
        vec![3, 4, 5, 6, 7]
    );
    let parts: Vec<(SweepMeta, Vec<SweepRow>)> = (0..2)
        .rev()
        .map(|i| {
            let m = meta(Shard { index: i, count: 2 });
            let rows = run_seeds(&m, &|_, _| {}).unwrap();
            (m, parse_rows_csv(&rows_csv(&rows), "shard").unwrap())
        })
        .collect();
    let (m, rows) = merge_sweeps(parts.clone()).unwrap();
    assert_eq!(m, whole_meta);
    assert_eq!(strip(&rows), strip(&whole));
    let (a, b) = (summarise(&m, &rows), summarise(&whole_meta, &whole));
    assert_eq!(
        without_timing(serde_json::to_value(&a).unwrap()),
        without_timing(serde_json::to_value(&b).unwrap())
    );
    assert_eq!(a.episodes, 5);

    let e = merge_sweeps(parts[..1].to_vec()).unwrap_err().to_string();
    assert!(e.contains("missing shard(s) 0/2"), "{e}");
    let e = merge_sweeps(vec![parts[0].clone(), parts[0].clone()])
        .unwrap_err()
        .to_string();
    assert!(e.contains("given twice"), "{e}");
    // shard 1/2 with shard 0/2 (parts[1]) changed by `edit`: the error
    let refused = |edit: &dyn Fn(&mut Part)| {
        let mut part = parts[1].clone();
        edit(&mut part);
        merge_sweeps(vec![parts[0].clone(), part])
            .unwrap_err()
            .to_string()
    };
    let e = refused(&|p| p.0.sets = vec!["steps=41".into()]);
    assert!(e.contains("another sweep"), "{e}");
    // shard 0/2 owns 3, 5, 7
    let e = refused(&|p| p.1[0].seed = 4);
    assert!(e.contains("not one of its seeds"), "{e}");
    // a seed of its own given twice in place of another (3, 3, 7), and one
    // left out: each names the shard and the seed
    let e = refused(&|p| p.1[1].seed = 3);
    assert!(e.contains("shard 0/2 holds seed 3 twice"), "{e}");
    let e = refused(&|p| {
        p.1.remove(1);
    });
    assert!(
        e.contains("shard 0/2 holds 2 of its 3 seeds: seed 5 is missing"),
        "{e}"
    );
    // a row whose safe flag contradicts its smallest h
    let text = rows_csv(&parts[0].1);
    let line = text.lines().nth(1).unwrap();
    let mut f: Vec<String> = line.split(',').map(String::from).collect();
    f[3] = if f[1] == "1" { "-1e999" } else { "inf" }.into();
    let bad = text.replacen(line, &f.join(","), 1);
    let e = parse_rows_csv(&bad, "sweep.csv").unwrap_err().to_string();
    assert!(
        e.contains("sweep.csv line 2: field 2 (safe)") && e.contains("field 4 (min_barrier)"),
        "{e}"
    );
}

#[test]
fn sweep_rows_do_not_depend_on_the_thread_count() {
    let m = meta(Shard::WHOLE);
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| run_seeds(&m, &|_, _| {}).unwrap());
    let two = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap()
        .install(|| run_seeds(&m, &|_, _| {}).unwrap());
    assert_eq!(strip(&one), strip(&two));
}

/// The double integrator with the term `0·√(edge)` added to its barrier
/// (NaN, an error, where `edge < 0`), 300 steps of seeds `seeds`.
fn stopping_meta(edge: &str, seeds: &str, shard: Shard) -> SweepMeta {
    let (_, text) = bayes_cbf_scenario::scenario::scenario_text("double-integrator").unwrap();
    let barrier = "h = \"p_max - p\"";
    assert!(text.contains(barrier));
    let text = text.replace(barrier, &format!("h = \"p_max - p + 0*sqrt({edge})\""));
    let dir = std::env::temp_dir().join(format!("sharding-stop-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join(format!("cart-{}.toml", edge.len()));
    std::fs::write(&file, text).unwrap();
    SweepMeta::new(
        file.to_str().unwrap(),
        &["steps=300".to_string()],
        seeds.parse().unwrap(),
        shard,
        1.0,
    )
    .unwrap()
}

/// A seed whose run stops with an error is a row of the sweep, not its
/// end. The double integrator's barrier with a term `0·√(e)` is NaN, an
/// error, where `e < 0`: at `e = 0.5 − p` on the seeds whose cart passes
/// p = 0.5 within 3 s and not on the others; at `e = −p` on every seed (each
/// crosses p = 0), which makes the sweep an error.
#[test]
fn a_seed_that_stops_is_a_row_and_every_seed_stopping_is_an_error() {
    let whole_meta = stopping_meta("0.5 - p", "73000..73010", Shard::WHOLE);
    let whole = run_seeds(&whole_meta, &|_, _| {}).unwrap();
    assert_eq!(whole.len(), 10);
    let (stopped, completed): (Vec<&SweepRow>, Vec<&SweepRow>) =
        whole.iter().partition(|r| r.error.is_some());
    assert!(!stopped.is_empty() && !completed.is_empty(), "{whole:?}");
    for r in &stopped {
        let e = r.error.as_deref().unwrap();
        assert!(
            e.starts_with("stopped at step ") && e.contains("NaN at state"),
            "{e}"
        );
        assert!(!r.safe && r.min_barrier.is_nan() && r.wall_time_s >= 0.0);
    }
    let s = summarise(&whole_meta, &whole);
    assert_eq!(s.stopped.count, stopped.len());
    assert_eq!(
        s.stopped_seeds.iter().map(|x| x.seed).collect::<Vec<_>>(),
        stopped.iter().map(|r| r.seed).collect::<Vec<_>>()
    );
    // a stopped run is neither safe nor among the unsafe seeds
    let safe = completed.iter().filter(|r| r.safe).count();
    assert_eq!(s.safe.count, safe);
    assert_eq!(s.unsafe_seeds.len(), completed.len() - safe);
    assert!(s.min_barrier.is_finite());
    assert_eq!(
        s.min_barrier,
        completed
            .iter()
            .map(|r| r.min_barrier)
            .fold(f64::INFINITY, f64::min)
    );
    assert!(s.no_infeasible_step.count <= completed.len());

    // through shards and sweep.csv, the same rows and summary
    let parts: Vec<(SweepMeta, Vec<SweepRow>)> = (0..2)
        .map(|i| {
            let m = stopping_meta("0.5 - p", "73000..73010", Shard { index: i, count: 2 });
            let rows = run_seeds(&m, &|_, _| {}).unwrap();
            (m, parse_rows_csv(&rows_csv(&rows), "shard").unwrap())
        })
        .collect();
    let (m, rows) = merge_sweeps(parts).unwrap();
    assert_eq!(strip(&rows), strip(&whole));
    assert_eq!(
        rows.iter().map(|r| r.error.clone()).collect::<Vec<_>>(),
        whole.iter().map(|r| r.error.clone()).collect::<Vec<_>>()
    );
    assert_eq!(
        without_timing(serde_json::to_value(summarise(&m, &rows)).unwrap()),
        without_timing(serde_json::to_value(&s).unwrap())
    );

    // every seed stopped: the scenario is at fault, whole or merged
    let all = stopping_meta("-p", "73000..73004", Shard::WHOLE);
    let e = run_seeds(&all, &|_, _| {}).unwrap_err().to_string();
    assert!(
        e.contains("every one of the 4 seeds stopped") && e.contains("seed 73000"),
        "{e}"
    );
    let parts: Vec<(SweepMeta, Vec<SweepRow>)> = (0..2)
        .map(|i| {
            let m = stopping_meta("-p", "73000..73004", Shard { index: i, count: 2 });
            let rows = run_seeds(&m, &|_, _| {}).unwrap();
            (m, rows)
        })
        .collect();
    let e = merge_sweeps(parts).unwrap_err().to_string();
    assert!(e.contains("every one of the 4 seeds stopped"), "{e}");
}

/// Shards of one scenario file merge whatever the spelling of its path;
/// a file edited between shards is refused, by the shard that runs it
/// (the sweep's description holds the scenario's digest) and by `merge`.
#[test]
fn shards_of_an_edited_scenario_file_do_not_merge() {
    let dir = std::env::temp_dir().join(format!("sharding-digest-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("cart.toml");
    let (_, text) = bayes_cbf_scenario::scenario::scenario_text("double-integrator").unwrap();
    std::fs::write(&file, &text).unwrap();
    let plain = file.to_str().unwrap().to_string();
    let dotted = dir
        .join(".")
        .join("cart.toml")
        .to_str()
        .unwrap()
        .to_string();
    let sets = ["steps=10".to_string()];
    let shard = |path: &str, index| {
        let m = SweepMeta::new(
            path,
            &sets,
            "0..4".parse().unwrap(),
            Shard { index, count: 2 },
            1.0,
        )
        .unwrap();
        let rows = run_seeds(&m, &|_, _| {}).unwrap();
        (m, rows)
    };
    let (a, b) = (shard(&plain, 0), shard(&dotted, 1));
    assert_ne!(a.0.scenario, b.0.scenario);
    merge_sweeps(vec![a.clone(), b]).unwrap();
    // described, then edited: the shard refuses to run it
    let described = SweepMeta::new(
        &plain,
        &sets,
        "0..4".parse().unwrap(),
        Shard { index: 1, count: 2 },
        1.0,
    )
    .unwrap();
    std::fs::write(&file, text.replace("mass = 2.0", "mass = 3.0")).unwrap();
    let e = run_seeds(&described, &|_, _| {}).unwrap_err().to_string();
    assert!(
        e.contains("is not the one the sweep was described with"),
        "{e}"
    );
    // described and run after the edit: merge refuses it beside the first
    let e = merge_sweeps(vec![a, shard(&plain, 1)])
        .unwrap_err()
        .to_string();
    assert!(e.contains("another sweep") && e.contains("digest"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A bad setting is one error before any seed runs (not a row per seed,
/// nor "every seed stopped"), in a shard that owns no seed too.
#[test]
fn a_bad_setting_stops_the_sweep_before_its_runs() {
    for (set, want) in [
        ("dt=-1", "dt = -1: must be finite and > 0"),
        ("controller.probability=2", "invalid probability = 2"),
        ("start=[1.0]", "start has 1 entries, expected 2"),
    ] {
        for shard in [Shard::WHOLE, Shard { index: 4, count: 5 }] {
            let sets = ["steps=10".to_string(), set.to_string()];
            let m = SweepMeta::new(
                "double-integrator",
                &sets,
                "0..3".parse().unwrap(),
                shard,
                1.0,
            )
            .unwrap();
            let e = run_seeds(&m, &|_, _| {}).unwrap_err().to_string();
            assert!(e.contains(want) && !e.contains("stopped"), "{set}: {e}");
        }
    }
}

/// `work(stop)` with `stop` set by another thread after `delay`: its
/// error, which must come within `limit`.
fn stopped_after<T: std::fmt::Debug>(
    delay: std::time::Duration,
    limit: std::time::Duration,
    work: impl FnOnce(&std::sync::Arc<std::sync::atomic::AtomicBool>) -> bayes_cbf_scenario::Result<T>,
) -> bayes_cbf_scenario::Error {
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let started = std::time::Instant::now();
    let r = std::thread::scope(|s| {
        s.spawn(|| {
            std::thread::sleep(delay);
            stop.store(true, std::sync::atomic::Ordering::Relaxed);
        });
        work(&stop)
    });
    let e = r.expect_err("interrupted, not finished");
    assert!(started.elapsed() < limit, "{:?}", started.elapsed());
    e
}

/// A stop flag set by another thread ends a run before its next step and a
/// sweep without rows: `Interrupted`, soon after, whatever was under way.
#[test]
fn a_stop_flag_interrupts_runs_and_sweeps() {
    use bayes_cbf_scenario::scenario::{self, run_scenario_until};
    use bayes_cbf_scenario::sweep::run_seeds_until;
    use std::sync::atomic::AtomicBool;
    use std::sync::Arc;
    use std::time::Duration;

    let interrupted = |e: &bayes_cbf_scenario::Error| {
        matches!(
            e.root(),
            bayes_cbf_scenario::Error::Core(bayes_cbf::Error::Interrupted)
        )
    };
    // 200 000 steps of the pendulum take minutes; the flag is set at 0.2 s
    let (sc, _) = scenario::load("pendulum-safe", &["steps=200000".to_string()]).unwrap();
    let e = stopped_after(Duration::from_millis(200), Duration::from_secs(5), |stop| {
        run_scenario_until(&sc, |_, _| {}, Arc::clone(stop)).map(|_| ())
    });
    assert!(interrupted(&e), "{e}");
    assert!(e.to_string().contains("scenario 'pendulum-safe'"), "{e}");

    let set = Arc::new(AtomicBool::new(true));
    let e = run_seeds_until(&meta(Shard::WHOLE), &|_, _| {}, &set).unwrap_err();
    assert!(interrupted(&e), "{e}");

    // the full calibration takes minutes; the flag is set at 0.3 s, and the
    // shard is an error, not a part holding the episodes that had ended
    let args = ExperimentArgs {
        seed: 5,
        quick: false,
    };
    let e = stopped_after(
        Duration::from_millis(300),
        Duration::from_secs(10),
        |stop| {
            calibration::run_shard_until(
                &args,
                &Options::default(),
                Shard::WHOLE,
                &|_: usize, _: usize| {},
                stop,
            )
        },
    );
    assert!(interrupted(&e), "{e}");
}
