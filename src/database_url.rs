//! The database URL the store connects to: the URL of `--database` with the password of
//! `--database-password-file` merged into it (the file's first line, percent-encoded into the
//! user information), so that the password need appear in no URL, variable or argument list. The
//! merged URL is only ever handed to the store; what is printed is [`redact_url`]'s.

use std::path::Path;

use anyhow::Context;

use facegate_store::redact_url;

/// [`database_url`] and the same URL as printed (its password redacted): what every command that
/// opens the database connects to, and names in its messages.
pub fn connect_and_shown(url: &str, password_file: Option<&Path>) -> anyhow::Result<(String, String)> {
    let url = database_url(url, password_file)?;
    let shown = redact_url(&url);
    Ok((url, shown))
}

/// `url` with the password of `password_file` (its first line) in it, or `url` as it is without a
/// file. Refused: a file for a SQLite URL (which has no password), a URL that already holds a
/// password, one that names no user, an unreadable file and one whose first line is empty. No
/// error holds the password or the URL's.
pub fn database_url(url: &str, password_file: Option<&Path>) -> anyhow::Result<String> {
    let Some(path) = password_file else { return Ok(url.to_string()) };
    let shown = redact_url(url);
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read the database password file {}", path.display()))?;
    let password = text.lines().next().unwrap_or_default();
    anyhow::ensure!(!password.is_empty(), "the database password file {} holds no password on its first line", path.display());
    let (scheme, rest) = url.split_once("://").with_context(|| format!("the database URL {shown} is not scheme://…"))?;
    anyhow::ensure!(
        matches!(scheme, "postgres" | "postgresql"),
        "--database-password-file (FACEGATE_DATABASE_PASSWORD_FILE) is for a PostgreSQL URL; {shown} has no password"
    );
    let authority_end = rest.find(['/', '?', '#']).unwrap_or(rest.len());
    let (authority, after) = rest.split_at(authority_end);
    let Some((user, host)) = authority.rsplit_once('@') else {
        anyhow::bail!("the database URL {shown} names no user: give postgres://USER@HOST/DB with --database-password-file");
    };
    anyhow::ensure!(
        !user.contains(':'),
        "the database URL {shown} holds a password and --database-password-file (FACEGATE_DATABASE_PASSWORD_FILE) gives one: \
         keep it only in the file"
    );
    Ok(format!("{scheme}://{user}:{}@{host}{after}", percent_encode(password)))
}

/// `text` with every byte but the URL's unreserved characters (`A-Z a-z 0-9 - . _ ~`) as `%XX`.
fn percent_encode(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'.' | b'_' | b'~' => (b as char).to_string(),
            _ => format!("%{b:02X}"),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(name: &str, text: &str) -> std::path::PathBuf {
        let path = std::env::temp_dir().join(format!("facegate-db-password-{name}-{}", std::process::id()));
        std::fs::write(&path, text).unwrap();
        path
    }

    #[test]
    fn the_password_file_is_merged_encoded_and_never_shown() {
        let path = file("merged", "p@ss/w:rd?\nignored second line\n");
        let url = database_url("postgres://facegate@db.internal:5432/facegate?sslmode=require", Some(&path)).unwrap();
        assert_eq!(url, "postgres://facegate:p%40ss%2Fw%3Ard%3F@db.internal:5432/facegate?sslmode=require");
        assert_eq!(redact_url(&url), "postgres://facegate:***@db.internal:5432/facegate?sslmode=require");
        assert_eq!(database_url("sqlite://x.db", None).unwrap(), "sqlite://x.db");
        for (url, expected) in [
            ("sqlite://x.db", "for a PostgreSQL URL"),
            ("postgres://db.internal/facegate", "names no user"),
            ("postgres://facegate:s3cretpw@db.internal/facegate", "holds a password"),
        ] {
            let error = format!("{:#}", database_url(url, Some(&path)).unwrap_err());
            assert!(error.contains(expected), "{url}: {error}");
            assert!(!error.contains("s3cretpw") && !error.contains("p@ss"), "{error}");
        }
        let empty = file("empty", "\nsecond\n");
        assert!(format!("{:#}", database_url("postgres://u@h/d", Some(&empty)).unwrap_err()).contains("no password"));
        let _ = std::fs::remove_file(path);
        let _ = std::fs::remove_file(empty);
    }
}
