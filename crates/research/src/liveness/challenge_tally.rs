//! The challenge evaluation's tally: attempts counted by kind and by live person, the depth
//! test's readings of the attempts whose poses were right, and the refusals' reasons.

use std::collections::BTreeMap;

use facegate_service::challenge::{self as rule, ChallengeOutcome};
use facegate_vision::liveness::head_turn::Turn;

use super::{Attempt, KindRow};

/// The attempts' verdicts, counted by kind and by live person.
#[derive(Default)]
pub struct Tally {
    pub rows: BTreeMap<String, (KindRow, BTreeMap<String, usize>)>,
    pub depth: BTreeMap<String, Vec<(f64, f64, f64)>>,
    pub live_refused: BTreeMap<String, (usize, String)>,
    pub live_by_person: BTreeMap<String, (usize, usize)>,
    pub judge_ms: f64,
    pub judged: usize,
    pub steps: usize,
}

impl Tally {
    pub fn add(&mut self, attempt: &Attempt, (outcome, enforce, ms, refusal): (ChallengeOutcome, bool, f64, Option<&'static str>)) {
        self.judge_ms += ms;
        self.judged += 1;
        self.steps += attempt.steps.len();
        let kind = attempt.kind.clone();
        let entry = self.rows.entry(kind.clone()).or_insert_with(|| {
            let row = KindRow {
                kind: kind.clone(),
                attempts: 0,
                passed_challenge: 0,
                passed_enforce: 0,
                shift_median: None,
                z_median: None,
                reasons: Vec::new(),
            };
            (row, BTreeMap::new())
        });
        entry.0.attempts += 1;
        entry.0.passed_challenge += outcome.passed as usize;
        entry.0.passed_enforce += enforce as usize;
        let poses_right = !outcome.steps.is_empty() && outcome.steps.iter().all(|s| s.ok);
        if let (true, Some(d)) = (poses_right, outcome.depth) {
            let excess = outcome.steps.iter().filter(|s| s.turn != Turn::Front).filter_map(|s| s.excess_turn()).fold(0.0f32, f32::max);
            self.depth.entry(kind.clone()).or_default().push((d.shift, d.z(rule::NOISE_FLOOR), f64::from(excess)));
        }
        let live = kind.starts_with("live");
        if live {
            let person = self.live_by_person.entry(format!("{} ({kind})", attempt.person)).or_default();
            person.0 += 1;
            person.1 += enforce as usize;
        }
        let reason = outcome.reason.clone().or_else(|| refusal.map(str::to_string));
        if let Some(reason) = &reason {
            *entry.1.entry(reason_class(reason)).or_default() += 1;
            if live {
                self.live_refused.entry(format!("{} ({kind})", attempt.person)).or_insert_with(|| (0, reason.clone())).0 += 1;
            }
        }
    }

    pub fn rows(&self) -> Vec<KindRow> {
        self.rows
            .values()
            .map(|(row, reasons)| {
                let mut row = row.clone();
                let depth = self.depth.get(&row.kind).cloned().unwrap_or_default();
                row.shift_median = median(&depth.iter().map(|d| d.0).collect::<Vec<_>>());
                row.z_median = median(&depth.iter().map(|d| d.1).collect::<Vec<_>>());
                let mut reasons: Vec<(String, usize)> = reasons.clone().into_iter().collect();
                reasons.sort_by(|a, b| b.1.cmp(&a.1));
                reasons.truncate(3);
                row.reasons = reasons;
                row
            })
            .collect()
    }
}

/// A failure reason without its numbers, to count alike ones together.
fn reason_class(reason: &str) -> String {
    if reason.contains("yaw") {
        "a step's yaw outside its range".into()
    } else if reason.contains("narrowed") {
        "the face narrowed beyond its turn".into()
    } else if reason.contains("rendered") {
        "a rendered head".into()
    } else if reason.contains("another person") {
        "a step shows another person".into()
    } else if reason.contains("no head's depth") {
        "no head's depth".into()
    } else {
        reason.chars().take(60).collect()
    }
}

fn median(values: &[f64]) -> Option<f64> {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied()
}
