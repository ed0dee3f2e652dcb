//! Reading a cascade from OpenCV's `opencv-cascade-classifier` XML: the window, the Haar features
//! and the stages' trees, each checked so that a malformed file is a typed error, never a panic or
//! a loop that does not end.

use std::path::Path;

use super::{Cascade, Feature, Node, Stage, Weak, model_error};
use crate::DetectError;

impl Cascade {
    pub fn load(path: &Path) -> Result<Cascade, DetectError> {
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| model_error(&name, e.to_string()))?;
        Cascade::parse(&text, &name)
    }

    /// Parse the XML text of a cascade (`name` is used in error messages only).
    pub fn parse(text: &str, name: &str) -> Result<Cascade, DetectError> {
        let err = |m: String| model_error(name, m);
        let doc = roxmltree::Document::parse(text).map_err(|e| err(format!("not valid XML: {e}")))?;
        let cascade = doc
            .descendants()
            .find(|n| n.has_tag_name("cascade"))
            .ok_or_else(|| err("no <cascade> element (old-style OpenCV 1.x cascades are not supported)".into()))?;
        let stage_type = text_of(cascade, "stageType", name)?;
        let feature_type = text_of(cascade, "featureType", name)?;
        if stage_type != "BOOST" || feature_type != "HAAR" {
            return Err(err(format!("unsupported cascade type {stage_type}/{feature_type} (BOOST/HAAR only)")));
        }
        let parse_usize = |s: String| s.parse::<usize>().map_err(|_| err(format!("bad integer {s:?}")));
        let window_width = parse_usize(text_of(cascade, "width", name)?)?;
        let window_height = parse_usize(text_of(cascade, "height", name)?)?;
        if !(4..=255).contains(&window_width) || !(4..=255).contains(&window_height) {
            return Err(err(format!("window {window_width}x{window_height} out of range")));
        }
        let features_node = child(cascade, "features").ok_or_else(|| err("missing <features>".into()))?;
        let features =
            items(features_node).into_iter().map(|f| parse_feature(f, window_width, window_height, name)).collect::<Result<Vec<_>, _>>()?;
        let stages_node = child(cascade, "stages").ok_or_else(|| err("missing <stages>".into()))?;
        let mut trees = Trees::default();
        let mut stages = Vec::new();
        for s in items(stages_node) {
            stages.push(trees.parse_stage(s, features.len(), name)?);
        }
        if stages.is_empty() {
            return Err(err("cascade has no stages".into()));
        }
        let Trees { weaks, nodes, leaves } = trees;
        Ok(Cascade { window_width, window_height, features, stages, weaks, nodes, leaves })
    }
}

fn child<'a, 'i>(parent: roxmltree::Node<'a, 'i>, tag: &str) -> Option<roxmltree::Node<'a, 'i>> {
    parent.children().find(|n| n.has_tag_name(tag))
}

fn items<'a, 'i>(parent: roxmltree::Node<'a, 'i>) -> Vec<roxmltree::Node<'a, 'i>> {
    parent.children().filter(|n| n.is_element()).collect()
}

/// The trimmed text of `parent`'s child `tag`.
fn text_of(parent: roxmltree::Node<'_, '_>, tag: &str, name: &str) -> Result<String, DetectError> {
    child(parent, tag).and_then(|n| n.text()).map(|t| t.trim().to_string()).ok_or_else(|| model_error(name, format!("missing <{tag}>")))
}

/// The whitespace-separated numbers of `s`.
fn numbers(s: &str, name: &str) -> Result<Vec<f64>, DetectError> {
    s.split_whitespace().map(|v| v.parse::<f64>().map_err(|_| model_error(name, format!("bad number {v:?}")))).collect()
}

/// One Haar feature: up to three weighted rectangles inside the window.
fn parse_feature(f: roxmltree::Node<'_, '_>, window_width: usize, window_height: usize, name: &str) -> Result<Feature, DetectError> {
    let err = |m: String| model_error(name, m);
    if let Some(t) = child(f, "tilted").and_then(|n| n.text())
        && t.trim() != "0"
    {
        return Err(err("tilted (45°) Haar features are not supported".into()));
    }
    let rects_node = child(f, "rects").ok_or_else(|| err("feature without <rects>".into()))?;
    let mut feature = Feature { rects: [[0; 4]; 3], weights: [0.0; 3], count: 0 };
    for r in items(rects_node) {
        let v = numbers(r.text().unwrap_or(""), name)?;
        if v.len() != 5 || feature.count == 3 {
            return Err(err("a feature rectangle needs `x y w h weight`, at most 3 per feature".into()));
        }
        let (x, y, w, h) = (v[0], v[1], v[2], v[3]);
        if x < 0.0 || y < 0.0 || w <= 0.0 || h <= 0.0 || x + w > window_width as f64 || y + h > window_height as f64 {
            return Err(err(format!("feature rectangle {v:?} leaves the window")));
        }
        let i = feature.count as usize;
        feature.rects[i] = [x as u8, y as u8, w as u8, h as u8];
        feature.weights[i] = v[4] as f32;
        feature.count += 1;
    }
    if feature.count == 0 {
        return Err(err("feature without rectangles".into()));
    }
    Ok(feature)
}

/// The weak classifiers' trees of the stages parsed so far, flattened.
#[derive(Default)]
struct Trees {
    weaks: Vec<Weak>,
    nodes: Vec<Node>,
    leaves: Vec<f32>,
}

impl Trees {
    /// One stage: its threshold and its weak classifiers' trees, appended to the flat lists.
    fn parse_stage(&mut self, s: roxmltree::Node<'_, '_>, feature_count: usize, name: &str) -> Result<Stage, DetectError> {
        let err = |m: String| model_error(name, m);
        let threshold =
            numbers(&text_of(s, "stageThreshold", name)?, name)?.first().copied().ok_or_else(|| err("empty stage threshold".into()))?;
        let weak_node = child(s, "weakClassifiers").ok_or_else(|| err("stage without <weakClassifiers>".into()))?;
        let first_weak = self.weaks.len() as u32;
        for w in items(weak_node) {
            self.parse_tree(w, feature_count, name)?;
        }
        Ok(Stage { first_weak, weak_count: self.weaks.len() as u32 - first_weak, threshold: threshold as f32 })
    }

    /// One weak classifier's tree: nodes that point forward, to a node or an existing leaf.
    fn parse_tree(&mut self, w: roxmltree::Node<'_, '_>, feature_count: usize, name: &str) -> Result<(), DetectError> {
        let err = |m: String| model_error(name, m);
        let internal = numbers(&text_of(w, "internalNodes", name)?, name)?;
        let leaf_values = numbers(&text_of(w, "leafValues", name)?, name)?;
        if internal.is_empty() || internal.len() % 4 != 0 {
            return Err(err("internalNodes must hold groups of `left right feature threshold`".into()));
        }
        let node_count = internal.len() / 4;
        for n in internal.chunks(4) {
            let (left, right, feature) = (n[0] as i32, n[1] as i32, n[2]);
            if feature < 0.0 || feature as usize >= feature_count {
                return Err(err(format!("node refers to feature {feature}, only {feature_count} exist")));
            }
            // Children must point forward to a node or to an existing leaf, so evaluation ends.
            for c in [left, right] {
                let ok = if c > 0 { (c as usize) < node_count } else { ((-c) as usize) < leaf_values.len() };
                if !ok {
                    return Err(err(format!("tree child {c} is out of range")));
                }
            }
            self.nodes.push(Node { feature: feature as u32, threshold: n[3] as f32, left, right });
        }
        // A tree whose nodes could loop would never end: OpenCV trees only point forward.
        let base = self.nodes.len() - node_count;
        if self.nodes[base..]
            .iter()
            .enumerate()
            .any(|(i, n)| (n.left > 0 && n.left as usize <= i) || (n.right > 0 && n.right as usize <= i))
        {
            return Err(err("tree nodes must point forward".into()));
        }
        self.weaks.push(Weak { first_node: base as u32, first_leaf: self.leaves.len() as u32 });
        self.leaves.extend(leaf_values.iter().map(|&v| v as f32));
        Ok(())
    }
}
