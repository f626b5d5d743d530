//! rosbag2's sqlite3 storage: a `topics` table (id, name, type, serialization_format, ...) and a
//! `messages` table (id, topic_id, timestamp in nanoseconds, data). The scan reads each row's
//! size and head in SQL (`substr`), so images are not read twice; a database damaged part way
//! keeps the rows read before the damage.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Mutex;

use rusqlite::{Connection, OpenFlags};

use super::{BagError, FileScan, HEAD_BYTES, Location, SMALL_MESSAGE_BYTES, Storage};

fn error(path: &Path, e: rusqlite::Error) -> BagError {
    if e.sqlite_error_code() == Some(rusqlite::ErrorCode::DatabaseCorrupt) {
        // SQLite reads its schema before any table: a file cut short before the pages the
        // schema points at cannot be opened at all, unlike a cut-short MCAP file.
        return BagError::format(
            path,
            format!(
                "sqlite3: {e}: the database is damaged (cut short?) where SQLite keeps its \
                 tables, so no message can be read; `sqlite3 {} .recover | sqlite3 \
                 recovered.db3` salvages what it can",
                path.display()
            ),
        );
    }
    BagError::format(path, format!("sqlite3: {e}"))
}

/// Scans one `.db3` file.
pub(crate) fn scan(path: &Path, number: usize) -> Result<FileScan, BagError> {
    if !path.is_file() {
        return Err(BagError::io(
            path,
            std::io::Error::new(std::io::ErrorKind::NotFound, "bag file not found"),
        ));
    }
    let connection = Connection::open_with_flags(
        path,
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )
    .map_err(|e| error(path, e))?;
    let mut topics: HashMap<i64, (String, String)> = HashMap::new();
    {
        let mut statement = connection
            .prepare("SELECT id, name, type, serialization_format FROM topics")
            .map_err(|e| error(path, e))?;
        let rows = statement
            .query_map([], |row| {
                Ok((
                    row.get::<_, i64>(0)?,
                    row.get::<_, String>(1)?,
                    row.get::<_, String>(2)?,
                    row.get::<_, String>(3)?,
                ))
            })
            .map_err(|e| error(path, e))?;
        for row in rows {
            let (id, name, type_name, format) = row.map_err(|e| error(path, e))?;
            if format != "cdr" {
                return Err(BagError::format(
                    path,
                    format!("topic {name} is serialized as {format:?}; this reader reads cdr"),
                ));
            }
            topics.insert(id, (name, type_name));
        }
    }
    let mut messages = Vec::new();
    let mut damage = None;
    {
        let query = format!(
            "SELECT id, topic_id, timestamp, length(data), \
             CASE WHEN length(data) <= {SMALL_MESSAGE_BYTES} THEN data \
             ELSE substr(data, 1, {HEAD_BYTES}) END FROM messages ORDER BY id"
        );
        let mut statement = connection.prepare(&query).map_err(|e| error(path, e))?;
        let mut rows = statement.query([]).map_err(|e| error(path, e))?;
        loop {
            let row = match rows.next() {
                Ok(Some(row)) => row,
                Ok(None) => break,
                Err(e) => {
                    damage = Some(format!("sqlite3 stopped reading messages: {e}"));
                    break;
                }
            };
            let read = (|| -> rusqlite::Result<_> {
                Ok((
                    row.get::<_, i64>(0)?,
                    row.get::<_, i64>(1)?,
                    row.get::<_, i64>(2)?,
                    row.get::<_, i64>(3)?,
                    row.get::<_, Vec<u8>>(4)?,
                ))
            })();
            let (id, topic_id, timestamp, size, head) = match read {
                Ok(fields) => fields,
                Err(e) => {
                    damage = Some(format!("message row {} does not read: {e}", messages.len()));
                    break;
                }
            };
            let Some((topic, type_name)) = topics.get(&topic_id) else {
                damage = Some(format!(
                    "message row {id} is on topic id {topic_id}, which the topics table lacks"
                ));
                break;
            };
            messages.push((
                topic.clone(),
                type_name.clone(),
                timestamp.max(0) as u64,
                size.max(0) as usize,
                head,
                Location::Sqlite { file: number, id },
            ));
        }
    }
    Ok(FileScan {
        storage: Storage::Sqlite(Mutex::new(connection)),
        messages,
        damage,
    })
}

/// Reads one message's payload again.
pub(crate) fn read(
    path: &Path,
    connection: &Mutex<Connection>,
    location: Location,
) -> Result<Vec<u8>, BagError> {
    let Location::Sqlite { id, .. } = location else {
        unreachable!("an MCAP location in an sqlite3 file")
    };
    let connection = connection.lock().unwrap_or_else(|e| e.into_inner());
    connection
        .query_row("SELECT data FROM messages WHERE id = ?1", [id], |row| {
            row.get::<_, Vec<u8>>(0)
        })
        .map_err(|e| error(path, e))
}
