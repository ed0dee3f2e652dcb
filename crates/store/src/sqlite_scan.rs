//! The gallery's start-up read of a SQLite file through SQLite's C API (`libsqlite3-sys`, the
//! library sqlx itself links): sqlx hands SQLite rows one at a time from its worker thread to the
//! async caller, about 6 µs a row on this machine, a minute and a half for ten million templates.
//! Here the caller's blocking thread steps the statement on a read-only connection and hands each
//! row, borrowed from SQLite, to the caller, which groups the rows by subject as it does sqlx's
//! rows: nothing of a row is copied but what the gallery keeps.
//!
//! Only this read takes the path: every write, and every other read, goes through the pool.

use std::ffi::{CStr, CString, c_int};
use std::path::Path;
use std::ptr::{NonNull, null, null_mut};

use libsqlite3_sys as ffi;

use crate::codec::StoredRow;
use crate::gallery_part::{GalleryPart, gallery_statement};

/// An open read-only connection, closed on drop.
struct Connection(NonNull<ffi::sqlite3>);

/// A prepared statement, finalised on drop.
struct Statement<'c> {
    raw: NonNull<ffi::sqlite3_stmt>,
    connection: &'c Connection,
}

impl Drop for Connection {
    fn drop(&mut self) {
        // SAFETY: the handle came from sqlite3_open_v2 and every statement on it (which borrows
        // the connection) is finalised before.
        unsafe { ffi::sqlite3_close(self.0.as_ptr()) };
    }
}

impl Drop for Statement<'_> {
    fn drop(&mut self) {
        // SAFETY: the statement came from sqlite3_prepare_v2 and is finalised once.
        unsafe { ffi::sqlite3_finalize(self.raw.as_ptr()) };
    }
}

impl Connection {
    fn open(path: &Path) -> Result<Connection, String> {
        let c_path = CString::new(path.as_os_str().as_encoded_bytes()).map_err(|_| format!("{}: a NUL in the path", path.display()))?;
        let mut raw = null_mut();
        // SAFETY: a valid C string and an out-pointer; the result is checked below.
        let rc = unsafe { ffi::sqlite3_open_v2(c_path.as_ptr(), &mut raw, ffi::SQLITE_OPEN_READONLY | ffi::SQLITE_OPEN_NOMUTEX, null()) };
        let connection =
            NonNull::new(raw).map(Connection).ok_or_else(|| format!("{}: SQLite could not allocate a connection", path.display()))?;
        if rc != ffi::SQLITE_OK {
            return Err(format!("{}: {}", path.display(), connection.error()));
        }
        // SAFETY: an open connection. The writers hold their locks for one enrolment at most.
        unsafe { ffi::sqlite3_busy_timeout(connection.0.as_ptr(), 5000) };
        Ok(connection)
    }

    fn error(&self) -> String {
        // SAFETY: an open connection; SQLite returns a NUL-terminated message it owns.
        unsafe { CStr::from_ptr(ffi::sqlite3_errmsg(self.0.as_ptr())) }.to_string_lossy().into_owned()
    }

    fn prepare(&self, sql: &str) -> Result<Statement<'_>, String> {
        let c_sql = CString::new(sql).expect("the statement has no NUL");
        let mut raw = null_mut();
        // SAFETY: an open connection, a valid C string, an out-pointer.
        let rc = unsafe { ffi::sqlite3_prepare_v2(self.0.as_ptr(), c_sql.as_ptr(), -1, &mut raw, null_mut()) };
        match NonNull::new(raw) {
            Some(raw) if rc == ffi::SQLITE_OK => Ok(Statement { raw, connection: self }),
            _ => Err(self.error()),
        }
    }
}

impl Statement<'_> {
    fn bind_text(&mut self, index: c_int, text: &str) -> Result<(), String> {
        // SAFETY: a prepared statement; SQLITE_TRANSIENT makes SQLite copy the bytes.
        let rc =
            unsafe { ffi::sqlite3_bind_text(self.raw.as_ptr(), index, text.as_ptr().cast(), text.len() as c_int, ffi::SQLITE_TRANSIENT()) };
        if rc == ffi::SQLITE_OK { Ok(()) } else { Err(self.connection.error()) }
    }

    /// The next row, or `None` when done.
    fn step(&mut self) -> Result<Option<()>, String> {
        // SAFETY: a prepared statement with its parameters bound.
        match unsafe { ffi::sqlite3_step(self.raw.as_ptr()) } {
            ffi::SQLITE_ROW => Ok(Some(())),
            ffi::SQLITE_DONE => Ok(None),
            _ => Err(self.connection.error()),
        }
    }

    fn int(&self, column: c_int) -> i64 {
        // SAFETY: the statement is on a row and `column` is one of its columns.
        unsafe { ffi::sqlite3_column_int64(self.raw.as_ptr(), column) }
    }

    /// A TEXT or BLOB column's bytes, `None` for NULL; valid until the next step (which takes the
    /// statement mutably, so the borrow cannot outlive it).
    fn bytes(&self, column: c_int) -> Option<&[u8]> {
        let stmt = self.raw.as_ptr();
        // SAFETY: the statement is on a row; the pointer is valid for `len` bytes until the next
        // step or finalisation, both of which need `&mut self` or ownership (a NULL column has
        // no pointer).
        unsafe {
            if ffi::sqlite3_column_type(stmt, column) == ffi::SQLITE_NULL {
                return None;
            }
            let data = ffi::sqlite3_column_blob(stmt, column).cast::<u8>();
            let len = ffi::sqlite3_column_bytes(stmt, column) as usize;
            Some(if data.is_null() || len == 0 { &[] } else { std::slice::from_raw_parts(data, len) })
        }
    }

    fn text(&self, column: c_int) -> Result<Option<&str>, String> {
        self.bytes(column).map(|b| std::str::from_utf8(b).map_err(|_| format!("column {column} is not UTF-8"))).transpose()
    }
}

/// `part` of `model_version`'s gallery rows from the SQLite file at `path`, in subject id order,
/// each handed to `each`; stops early when `each` returns false (the reader is gone). Blocking:
/// run it on a thread of its own.
pub(crate) fn read_gallery_part(
    path: &Path,
    model_version: &str,
    part: &GalleryPart,
    mut each: impl FnMut(StoredRow<'_>) -> bool,
) -> Result<(), String> {
    let connection = Connection::open(path)?;
    let mut statement = connection.prepare(&gallery_statement(part, |n| format!("?{n}")))?;
    statement.bind_text(1, model_version)?;
    statement.bind_text(2, part.after.as_deref().unwrap_or(""))?;
    if let Some(through) = &part.through {
        statement.bind_text(3, through)?;
    }
    while statement.step()?.is_some() {
        let missing = |what: &str| format!("a template row without {what}");
        let row = StoredRow {
            id: statement.int(0),
            subject: statement.text(1)?.ok_or_else(|| missing("subject"))?,
            model_version: statement.text(2)?.ok_or_else(|| missing("model version"))?,
            dimension: statement.int(3),
            vector: statement.bytes(4).ok_or_else(|| missing("vector"))?,
            key_id: statement.text(5)?,
            data_key: statement.bytes(6),
        };
        if !each(row) {
            break;
        }
    }
    Ok(())
}
