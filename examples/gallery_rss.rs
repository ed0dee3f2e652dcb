//! Memory of the identification gallery: the resident set (`/proc/self/statm`) before and after
//! loading N synthetic 128-d templates (one per subject, ids like the service's), in a fresh
//! process per size. `cargo run --release --example gallery_rss -- 10000 100000 1000000`
//! (each size is run in a child process of its own).

use facegate::recognize::Template;
use facegate::service::gallery::Gallery;
use rand::{Rng, SeedableRng};

fn resident_bytes() -> u64 {
    let statm = std::fs::read_to_string("/proc/self/statm").expect("/proc/self/statm (Linux)");
    let pages: u64 = statm.split_whitespace().nth(1).and_then(|p| p.parse().ok()).expect("resident pages");
    pages * 4096
}

fn main() {
    let sizes: Vec<usize> = std::env::args().skip(1).map(|a| a.parse().expect("a template count")).collect();
    if let [n] = sizes[..] {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(15);
        let before = resident_bytes();
        let mut gallery = Gallery::new("bench");
        for i in 0..n {
            let template = Template::new("bench", (0..128).map(|_| rng.random_range(-1.0f32..1.0)).collect());
            gallery.add(&format!("subject-{i:07}"), &[template]);
        }
        let after = resident_bytes();
        let growth = after.saturating_sub(before);
        println!(
            "{n} templates: RSS {:.1} MB -> {:.1} MB, growth {:.1} MB, {:.0} bytes per template",
            before as f64 / 1e6,
            after as f64 / 1e6,
            growth as f64 / 1e6,
            growth as f64 / n as f64
        );
        std::hint::black_box(&gallery);
        return;
    }
    let sizes = if sizes.is_empty() { vec![10_000, 100_000, 1_000_000] } else { sizes };
    for n in sizes {
        let status = std::process::Command::new(std::env::current_exe().expect("this example's path")).arg(n.to_string()).status();
        assert!(status.expect("runs").success());
    }
}
