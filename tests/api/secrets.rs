//! No database password in any output of a failed start-up: `facegate serve` (text and JSON log
//! formats) and the store commands on a PostgreSQL URL whose server cannot be reached, the
//! password in the URL or in `--database-password-file`; the error names the URL redacted.

use crate::fail_closed::{Scratch, facegate};

const PASSWORD: &str = "s3cretpw";

/// `facegate args…` fails, says what it could not open with the URL redacted, and prints the
/// password nowhere (stdout or stderr).
fn fails_without_the_password(args: &[&str], expected: &str) {
    let out = facegate(args);
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(!out.status.success(), "{args:?} started:\n{stdout}\n{stderr}");
    assert!(!stdout.contains(PASSWORD) && !stderr.contains(PASSWORD), "{args:?} printed the password:\n{stdout}\n{stderr}");
    assert!(stderr.contains(expected), "{args:?}: {expected:?} not in:\n{stderr}");
}

#[test]
fn a_failed_start_up_never_prints_the_database_password() {
    let scratch = Scratch::new("secrets");
    let with_password = format!("postgres://u:{PASSWORD}@127.0.0.1:1/db");
    let password_file = scratch.path("db-password");
    std::fs::write(&password_file, format!("{PASSWORD}\n")).unwrap();
    let shown = "postgres://u:***@127.0.0.1:1/db";
    for format in ["text", "json"] {
        fails_without_the_password(&["serve", "--bind", "127.0.0.1:0", "--log-format", format, "--database", &with_password], shown);
        fails_without_the_password(
            &[
                "serve",
                "--bind",
                "127.0.0.1:0",
                "--log-format",
                format,
                "--database",
                "postgres://u@127.0.0.1:1/db",
                "--database-password-file",
                &password_file,
            ],
            shown,
        );
    }
    // A malformed URL is refused naming it, redacted.
    fails_without_the_password(
        &["serve", "--bind", "127.0.0.1:0", "--database", &format!("mysql://u:{PASSWORD}@h/db")],
        "mysql://u:***@h/db",
    );
    // The store commands open the same database the same way.
    fails_without_the_password(&["calibrate", "--database", &with_password], shown);
    fails_without_the_password(&["rekey", "--database", "postgres://u@127.0.0.1:1/db", "--database-password-file", &password_file], "");
    fails_without_the_password(&["backup", &scratch.path("copy.db"), "--database", &with_password], shown);
    // Both at once: the password only in the file.
    fails_without_the_password(
        &["serve", "--bind", "127.0.0.1:0", "--database", &with_password, "--database-password-file", &password_file],
        "keep it only in the file",
    );
}
