//! A part of the gallery, the subjects between two ids, and the one SQL statement that reads it:
//! shared by the sqlx reads ([`crate::gallery`]) and the SQLite file scan ([`crate::sqlite_scan`]).

/// The gallery read of `part` (the columns [`crate::codec::StoredRow::of`] takes), its parameters named by
/// `placeholder` (`$n` for sqlx, `?n` for SQLite's C API): 1 the model version, 2 the lower bound
/// ('' sorts before every id, and ids are never empty), 3 the upper bound, left out of the
/// statement when there is none so that the index range ends where the part does.
pub(crate) fn gallery_statement(part: &GalleryPart, placeholder: impl Fn(usize) -> String) -> String {
    let through = match part.through {
        Some(_) => format!("AND t.subject_id <= {}", placeholder(3)),
        None => String::new(),
    };
    format!(
        "SELECT t.id, t.subject_id, t.model_version, t.dimension, t.vector, s.key_id, s.data_key
         FROM templates t JOIN subjects s ON s.id = t.subject_id
         WHERE t.model_version = {} AND t.subject_id > {} {through}
         ORDER BY t.subject_id, t.id",
        placeholder(1),
        placeholder(2)
    )
}

/// The subjects with ids after `after` and up to `through` (inclusive); `None` is unbounded.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct GalleryPart {
    pub after: Option<String>,
    pub through: Option<String>,
    /// About how many templates the part holds (0: not known), so that its reader can reserve
    /// its memory once rather than grow it by doubling.
    pub expected_templates: usize,
}

impl GalleryPart {
    /// The parts that `cuts` (increasing subject ids) make: up to the first, between each two,
    /// after the last.
    pub fn between(cuts: &[String]) -> Vec<GalleryPart> {
        let bounds: Vec<Option<String>> =
            std::iter::once(None).chain(cuts.iter().cloned().map(Some)).chain(std::iter::once(None)).collect();
        bounds.windows(2).map(|w| GalleryPart { after: w[0].clone(), through: w[1].clone(), expected_templates: 0 }).collect()
    }
}
