//! The identification gallery at scale: resident memory, search time and the quantised
//! shortlist's recall of the exact best subject, on N synthetic templates of DIMS values (one per
//! subject, ids like the service's), each size in a fresh process.
//!
//!   cargo run --release --example gallery_scale -- [--dims 256] [--probes 100] [--exact] [--protected] N...
//!
//! Per size it prints the resident-set growth of loading the gallery (`/proc/self/statm`) and
//! bytes per template, then for each probe (100 unless `--probes`) the search's wall time on this one thread (median and
//! 95th percentile; the kernel's thread CPU clock ticks too coarsely for a single search: run it
//! on an idle machine) and whether the exact best subject is in the shortlist (`Gallery::search` with
//! k = 1). Half the probes are genuine (an enrolled template plus noise of the same size: cosine
//! about 0.7 with it) and half random (an impostor's search, whose best scores lie close
//! together). The exact best is found by streaming the same seeded templates a second time (a
//! chunk of them against all probes is one matrix product), so
//! the exact gallery is never held. `--exact` holds the exact float gallery instead (the
//! `Precision::Exact` search, for the memory and time it costs at the same N).
//!
//! `--protected` holds what a service with protected templates holds (`--template-protection-key-file`):
//! every template turned by a keyed rotation (`service::protection`, a fixed secret here), and
//! each probe turned inside the timed search, as the protected engine turns it before the
//! gallery sees it. Rotations keep cosines, so the exact best is the same subject.
//!
//! `--database URL --version MODEL_VERSION` instead times the service's start-up load of a
//! store's gallery (`LiveGallery::load`, quantised) and its resident growth, then a search
//! (filled by `examples/fill_gallery.rs --bulk`).

use facegate_core::template::{OperatingPoint, Template};
use facegate_service::Matcher;
use facegate_service::gallery::{Found, Gallery, Precision};
use rand::{Rng, SeedableRng};

/// The deep recognizers' scoring (the best cosine) for templates of one model version.
struct MaxCosine(String);

impl Matcher for MaxCosine {
    fn model_version(&self) -> &str {
        &self.0
    }
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        enrolled.iter().map(|t| probe.cosine(t)).fold(f32::NEG_INFINITY, f32::max)
    }
    fn operating_point(&self, fmr: f64, _enrolled: usize) -> OperatingPoint {
        OperatingPoint { fmr, threshold: 0.5 }
    }
    fn max_cosine_scoring(&self) -> bool {
        true
    }
}

fn resident_bytes() -> u64 {
    let statm = std::fs::read_to_string("/proc/self/statm").expect("/proc/self/statm (Linux)");
    let pages: u64 = statm.split_whitespace().nth(1).and_then(|p| p.parse().ok()).expect("resident pages");
    pages * 4096
}

/// The templates, in chunks of a million, the same for the same seed.
fn templates(n: usize, dims: usize, mut each: impl FnMut(usize, &[f32])) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(15);
    let mut v = vec![0.0f32; dims];
    for i in 0..n {
        v.iter_mut().for_each(|x| *x = rng.random_range(-1.0f32..1.0));
        each(i, &v);
    }
}

fn id(i: usize) -> String {
    format!("subject-{i:08}")
}

/// The fixed secret `--protected` turns templates under.
const SECRET: &str = "5e1f0c3a9b7d2e4f6a8c0b1d3e5f7a9c2b4d6e8f0a1c3e5d7f9b0a2c4e6d8f1a";

fn one_size(n: usize, dims: usize, exact: bool, probe_count: usize, protected: bool) {
    let precision = if exact { Precision::Exact } else { Precision::Quantised };
    let rotation = protected.then(|| facegate_service::protection::ProtectionKey::parse(SECRET).expect("a key").rotation(dims));
    // Probes: even ones a noisy copy of an enrolled template, odd ones random.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(99);
    let mut genuine_rows = std::collections::BTreeMap::<usize, Vec<usize>>::new();
    for g in 0..probe_count / 2 {
        genuine_rows.entry(rng.random_range(0..n)).or_default().push(2 * g);
    }
    let mut probes: Vec<Vec<f32>> = vec![Vec::new(); probe_count];
    for probe in probes.iter_mut().skip(1).step_by(2) {
        *probe = (0..dims).map(|_| rng.random_range(-1.0f32..1.0)).collect();
    }
    let before = resident_bytes();
    let started = std::time::Instant::now();
    let mut gallery = Gallery::with_precision("bench", precision);
    templates(n, dims, |i, v| {
        let stored = rotation.as_ref().map_or_else(|| v.to_vec(), |r| r.apply(v));
        gallery.add(&id(i), &[Template::new("bench", stored)]);
        for &p in genuine_rows.get(&i).into_iter().flatten() {
            probes[p] = v.iter().map(|x| x + rng.random_range(-1.0f32..1.0)).collect();
        }
    });
    let load_s = started.elapsed().as_secs_f64();
    let growth = resident_bytes().saturating_sub(before);
    // The exact best of each probe, streaming the same templates again: a chunk of unit templates
    // against every unit probe is one matrix product.
    let probes: Vec<Template> = probes.into_iter().map(|p| Template::new("bench", p)).collect();
    let units: Vec<f32> = probes.iter().flat_map(|p| facegate_core::vector::unit(p.vector.clone())).collect();
    let units = faer::MatRef::from_row_major_slice(&units, probe_count, dims);
    let mut best: Vec<(f32, usize)> = vec![(f32::NEG_INFINITY, 0); probe_count];
    const CHUNK: usize = 4096;
    let (mut chunk, mut first) = (Vec::with_capacity(CHUNK * dims), 0);
    let mut cosines = faer::Mat::<f32>::zeros(CHUNK, probe_count);
    let mut flush = |chunk: &mut Vec<f32>, first: usize, best: &mut Vec<(f32, usize)>| {
        let rows = chunk.len() / dims;
        let lhs = faer::MatRef::from_row_major_slice(chunk, rows, dims);
        faer::linalg::matmul::matmul(
            cosines.as_mut().subrows_mut(0, rows),
            faer::Accum::Replace,
            lhs,
            units.transpose(),
            1.0f32,
            faer::Par::Seq,
        );
        let out = cosines.as_ref();
        for (p, b) in best.iter_mut().enumerate() {
            for r in 0..rows {
                if out[(r, p)] > b.0 {
                    *b = (out[(r, p)], first + r);
                }
            }
        }
        chunk.clear();
    };
    templates(n, dims, |i, v| {
        if chunk.is_empty() {
            first = i;
        }
        chunk.extend_from_slice(&facegate_core::vector::unit(v.to_vec()));
        if chunk.len() == CHUNK * dims {
            flush(&mut chunk, first, &mut best);
        }
    });
    if !chunk.is_empty() {
        flush(&mut chunk, first, &mut best);
    }
    let (mut times, mut found) = (Vec::new(), [0usize; 2]);
    for (p, probe) in probes.iter().enumerate() {
        let t = std::time::Instant::now();
        let turned = rotation.as_ref().map(|r| Template::new("bench", r.apply(&probe.vector)));
        let (result, _) = gallery.search(&MaxCosine("bench".into()), turned.as_ref().unwrap_or(probe), 1e-3, 1).expect("readable");
        times.push(t.elapsed().as_secs_f64() * 1e3);
        let hit = match result {
            Found::Shortlist(subjects) => subjects.contains(&id(best[p].1)),
            Found::Decided(candidates) => candidates[0].subject == id(best[p].1),
        };
        found[p % 2] += hit as usize;
    }
    times.sort_by(f64::total_cmp);
    let mean_genuine = best.iter().step_by(2).map(|b| b.0).sum::<f32>() / (probe_count / 2) as f32;
    println!(
        "| {n} | {dims} | {precision:?}{} | {:.0} MB | {:.0} | {load_s:.1} s | {:.2} ms | {:.2} ms | {}/{} (best cosine {mean_genuine:.2}) | {}/{} |",
        if protected { ", protected" } else { "" },
        growth as f64 / 1e6,
        growth as f64 / n as f64,
        times[probe_count / 2],
        times[probe_count * 95 / 100],
        found[0],
        probe_count / 2,
        found[1],
        probe_count / 2,
    );
}

fn main() {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let exact = args.iter().position(|a| a == "--exact").map(|i| args.remove(i)).is_some();
    let protected = args.iter().position(|a| a == "--protected").map(|i| args.remove(i)).is_some();
    let probes: usize = match args.iter().position(|a| a == "--probes") {
        Some(i) => {
            args.remove(i);
            args.remove(i).parse().expect("--probes takes a number")
        }
        None => 100,
    };
    let dims: usize = match args.iter().position(|a| a == "--dims") {
        Some(i) => {
            args.remove(i);
            args.remove(i).parse().expect("--dims takes a number")
        }
        None => 256,
    };
    if let Some(i) = args.iter().position(|a| a == "--database") {
        let database = args[i + 1].clone();
        let version = args.iter().position(|a| a == "--version").map(|i| args[i + 1].clone()).expect("--version MODEL_VERSION");
        return load_from(&database, &version);
    }
    let sizes: Vec<usize> = args.iter().map(|a| a.parse().expect("a template count")).collect();
    if let (Ok(_), [n]) = (std::env::var("GALLERY_SCALE_CHILD"), &sizes[..]) {
        one_size(*n, dims, exact, probes, protected);
        return;
    }
    println!(
        "| templates | values | precision | resident growth | bytes per template | load | search median (one thread) | p95 | genuine probes: exact best shortlisted | random probes: exact best shortlisted |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for n in if sizes.is_empty() { vec![10_000, 100_000, 1_000_000] } else { sizes } {
        let mut child = std::process::Command::new(std::env::current_exe().expect("this example's path"));
        child.env("GALLERY_SCALE_CHILD", "1").args(["--dims", &dims.to_string(), "--probes", &probes.to_string(), &n.to_string()]);
        if exact {
            child.arg("--exact");
        }
        if protected {
            child.arg("--protected");
        }
        assert!(child.status().expect("runs").success());
    }
}

fn load_from(database: &str, version: &str) {
    let runtime = tokio::runtime::Runtime::new().expect("a runtime");
    runtime.block_on(async {
        let store = facegate_store::Store::connect(database, None).await.expect("the database opens");
        let before = resident_bytes();
        let started = std::time::Instant::now();
        let live = facegate_service::gallery::LiveGallery::new(store.clone(), version, Precision::Quantised);
        let unreadable = live.load().await.expect("loads");
        let load_s = started.elapsed().as_secs_f64();
        let growth = resident_bytes().saturating_sub(before);
        let (subjects, templates) = live.size();
        assert!(unreadable.is_empty(), "unreadable subjects: {unreadable:?}");
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let dims = 256;
        let (mut scans, mut times) = (Vec::new(), Vec::new());
        let matcher = MaxCosine(version.to_string());
        for _ in 0..20 {
            let probe = Template::new(version, (0..dims).map(|_| rng.random_range(-1.0f32..1.0)).collect());
            let t = std::time::Instant::now();
            std::hint::black_box(live.search(&matcher, &probe, 1e-3, 5).expect("readable"));
            scans.push(t.elapsed().as_secs_f64() * 1e3);
            let t = std::time::Instant::now();
            let (candidates, _) = live.identify(&matcher, &probe, 1e-3, 5).await.expect("reads").expect("readable");
            times.push(t.elapsed().as_secs_f64() * 1e3);
            assert_eq!(candidates.len(), 5.min(subjects));
        }
        scans.sort_by(f64::total_cmp);
        times.sort_by(f64::total_cmp);
        println!(
            "{database}: {subjects} subjects, {templates} templates loaded in {load_s:.1} s; resident growth {:.0} MB ({:.0} bytes per template); scan median {:.2} ms; identify (scan + re-rank from the store) median {:.2} ms",
            growth as f64 / 1e6,
            growth as f64 / templates.max(1) as f64,
            scans[10],
            times[10]
        );
        store.close().await;
    });
}
