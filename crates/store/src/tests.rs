//! The migrators and the plain vector encoding; no database needed.

use sqlx::migrate::Migrator;

use crate::{POSTGRES_MIGRATIONS, SQLITE_MIGRATIONS, blob_to_vector, vector_to_blob};

/// Each backend's migrator has exactly the files of its own folder.
#[test]
fn each_backend_migrates_from_its_own_folder() {
    let versions = |migrator: &Migrator| migrator.iter().map(|m| m.version).collect::<Vec<i64>>();
    let files = |folder: &str| {
        let mut versions: Vec<i64> = std::fs::read_dir(facegate_paths::repository_dir().join(folder))
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file())
            .map(|p| p.file_name().unwrap().to_str().unwrap().split('_').next().unwrap().parse().unwrap())
            .collect();
        versions.sort();
        versions
    };
    assert_eq!(versions(&SQLITE_MIGRATIONS), files("migrations/sqlite"));
    assert_eq!(versions(&POSTGRES_MIGRATIONS), files("migrations/postgres"));
}

#[test]
fn blobs_round_trip_little_endian() {
    let v = [1.0f32, -0.5, 3.25e-7, f32::MAX];
    let blob = vector_to_blob(&v);
    assert_eq!(&blob[..4], &1.0f32.to_le_bytes());
    assert_eq!(blob_to_vector(&blob).unwrap(), v);
    assert!(blob_to_vector(&blob[..5]).is_none());
}
