//! The pairs CSV of `facegate eval pairs`: a header whose first two columns are `file_x,file_y`,
//! one pair per line in, `file_x,file_y,score` out, each image processed once.

use std::collections::HashMap;
use std::io::{BufRead, Write};
use std::path::Path;

use anyhow::Context;

use facegate_core::template::Template;

/// One pair of the pairs CSV.
#[derive(Debug, Clone, PartialEq)]
pub struct PairRow {
    pub file_x: String,
    pub file_y: String,
}

/// Read the pairs CSV: a header whose first two columns are `file_x,file_y`, then one pair per line
/// (further columns are ignored; fields may be double-quoted).
pub fn read_pairs(reader: impl BufRead) -> anyhow::Result<Vec<PairRow>> {
    let mut lines = reader.lines();
    let header = lines.next().context("the pairs file is empty")??;
    let cols = split_csv(&header);
    anyhow::ensure!(
        cols.len() >= 2 && cols[0] == "file_x" && cols[1] == "file_y",
        "the pairs file must start with a header `file_x,file_y,...`, found {header:?}"
    );
    let mut out = Vec::new();
    for (i, line) in lines.enumerate() {
        let line = line?;
        if line.trim().is_empty() {
            continue;
        }
        let cols = split_csv(&line);
        anyhow::ensure!(cols.len() >= 2, "line {}: expected at least two columns: {line:?}", i + 2);
        out.push(PairRow { file_x: cols[0].clone(), file_y: cols[1].clone() });
    }
    Ok(out)
}

fn split_csv(line: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut field = String::new();
    let mut quoted = false;
    let mut chars = line.trim_end_matches('\r').chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '"' if quoted && chars.peek() == Some(&'"') => {
                field.push('"');
                chars.next();
            }
            '"' => quoted = !quoted,
            ',' if !quoted => out.push(std::mem::take(&mut field)),
            c => field.push(c),
        }
    }
    out.push(field);
    out.into_iter().map(|f| f.trim().to_string()).collect()
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) { format!("\"{}\"", s.replace('"', "\"\"")) } else { s.to_string() }
}

/// Score every pair, processing each image once. `template_of` gives an image's template or the
/// reason it has none; such pairs get an empty score and a warning through `warn`.
pub fn score_pairs(
    pairs: &[PairRow],
    images: &Path,
    mut template_of: impl FnMut(&Path) -> anyhow::Result<Template>,
    score: impl Fn(&Template, &Template) -> f32,
    mut out: impl Write,
    mut warn: impl FnMut(String),
) -> anyhow::Result<()> {
    let mut cache: HashMap<&str, Option<Template>> = HashMap::new();
    writeln!(out, "file_x,file_y,score")?;
    for pair in pairs {
        for name in [&pair.file_x, &pair.file_y] {
            if !cache.contains_key(name.as_str()) {
                let t = match template_of(&images.join(name)) {
                    Ok(t) => Some(t),
                    Err(e) => {
                        warn(format!("{name}: no template ({e})"));
                        None
                    }
                };
                cache.insert(name, t);
            }
        }
        let s = match (&cache[pair.file_x.as_str()], &cache[pair.file_y.as_str()]) {
            (Some(a), Some(b)) => format!("{:.6}", score(a, b)),
            _ => {
                warn(format!("{},{}: empty score (an image has no face or could not be read)", pair.file_x, pair.file_y));
                String::new()
            }
        };
        writeln!(out, "{},{},{s}", csv_field(&pair.file_x), csv_field(&pair.file_y))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairs_csv_is_parsed_and_missing_faces_give_empty_scores() {
        let csv = "file_x,file_y,same\na.jpg,b.jpg,1\n\"c,1.jpg\",a.jpg,0\nnoface.jpg,b.jpg,0\n";
        let pairs = read_pairs(csv.as_bytes()).unwrap();
        assert_eq!(pairs.len(), 3);
        assert_eq!(pairs[1].file_x, "c,1.jpg");
        assert!(read_pairs("x,y\na,b\n".as_bytes()).is_err());
        assert!(read_pairs("file_x,file_y\nonly-one\n".as_bytes()).is_err());

        let mut calls = Vec::new();
        let mut out = Vec::new();
        let mut warnings = Vec::new();
        score_pairs(
            &pairs,
            Path::new("imgs"),
            |p| {
                calls.push(p.to_path_buf());
                anyhow::ensure!(!p.ends_with("noface.jpg"), "no face was found in the image");
                let name = p.file_name().unwrap().to_string_lossy().to_string();
                Ok(Template::new("v", vec![name.len() as f32, 1.0]))
            },
            |a, b| a.cosine(b),
            &mut out,
            |w| warnings.push(w),
        )
        .unwrap();
        // Each image processed once, relative to the images folder.
        assert_eq!(calls.len(), 4);
        assert_eq!(calls[0], Path::new("imgs/a.jpg"));
        let text = String::from_utf8(out).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "file_x,file_y,score");
        assert!(lines[1].starts_with("a.jpg,b.jpg,1.0000"), "{}", lines[1]);
        assert!(lines[2].starts_with("\"c,1.jpg\",a.jpg,0.99"), "{}", lines[2]);
        assert_eq!(lines[3], "noface.jpg,b.jpg,");
        assert_eq!(warnings.len(), 2);
    }
}
