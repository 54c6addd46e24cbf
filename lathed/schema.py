"""The record store's schema: its versioned migrations and the kinds of event it holds
(docs/records.md)."""
from __future__ import annotations

import difflib
import sqlite3

# Versioned schema migrations: (version, SQL). Append, never edit.
MIGRATIONS: list[tuple[int, str]] = [
    (1, """
    CREATE TABLE events (
        id      INTEGER PRIMARY KEY AUTOINCREMENT,
        uuid    TEXT NOT NULL UNIQUE,
        t       REAL NOT NULL,
        source  TEXT NOT NULL,
        kind    TEXT NOT NULL,
        payload TEXT NOT NULL
    );
    CREATE INDEX events_kind ON events(kind, id);
    """),
    (2, """
    ALTER TABLE events ADD COLUMN machine_id TEXT;

    -- one row per workpiece, written when it is finished (or aborted)
    CREATE TABLE workpieces (
        id                   INTEGER PRIMARY KEY AUTOINCREMENT,
        uuid                 TEXT NOT NULL UNIQUE,
        machine_id           TEXT NOT NULL,
        machine              TEXT NOT NULL,
        part_no              INTEGER,
        program              INTEGER,
        start_t              REAL NOT NULL,
        end_t                REAL NOT NULL,
        outcome              TEXT NOT NULL,        -- finished | aborted | partial
        max_chatter_index    REAL,
        chatter_threshold    REAL,
        chatter_alarms       INTEGER NOT NULL,
        chatter_frequency_hz REAL,
        compensation_um      REAL,
        rpm                  REAL,
        depth_mm             REAL,
        feed_mm_rev          REAL,
        tool                 TEXT,
        material             TEXT,
        abnormal             INTEGER NOT NULL,
        reason               TEXT
    );
    CREATE INDEX workpieces_abnormal ON workpieces(abnormal, id);

    -- post-process inspection: the second of the two-time quality detection
    CREATE TABLE inspections (
        id                INTEGER PRIMARY KEY AUTOINCREMENT,
        uuid              TEXT NOT NULL UNIQUE,
        machine_id        TEXT NOT NULL,
        t                 REAL NOT NULL,
        part_uuid         TEXT NOT NULL,
        ra_um             REAL,
        diameter_error_um REAL,
        measured          TEXT NOT NULL,          -- JSON: other measured values
        inspector         TEXT
    );
    CREATE INDEX inspections_part ON inspections(part_uuid, id);

    -- parts sent to sampling inspection; pending while no inspection joins
    CREATE TABLE sampling_queue (
        id         INTEGER PRIMARY KEY AUTOINCREMENT,
        uuid       TEXT NOT NULL UNIQUE,
        machine_id TEXT NOT NULL,
        t          REAL NOT NULL,
        part_uuid  TEXT NOT NULL UNIQUE,
        reason     TEXT NOT NULL
    );

    -- trials of designed (Taguchi) experiments, per tool holder and material
    CREATE TABLE experiments (
        id                INTEGER PRIMARY KEY AUTOINCREMENT,
        uuid              TEXT NOT NULL UNIQUE,
        machine_id        TEXT NOT NULL,
        t                 REAL NOT NULL,
        tool              TEXT NOT NULL,
        material          TEXT NOT NULL,
        run               INTEGER,
        levels            TEXT NOT NULL,          -- JSON {factor: level number}
        settings          TEXT NOT NULL,          -- JSON {factor: value}
        ra_um             REAL,
        diameter_error_um REAL,
        removal_rate      REAL,
        part_uuid         TEXT
    );
    CREATE INDEX experiments_tool ON experiments(tool, material, id);

    CREATE TABLE outbox (
        id     INTEGER PRIMARY KEY AUTOINCREMENT,
        tbl    TEXT NOT NULL,
        row_id INTEGER NOT NULL
    );
    INSERT INTO outbox(tbl, row_id) SELECT 'events', id FROM events ORDER BY id;
    CREATE TABLE forward_progress (
        sink      TEXT PRIMARY KEY,
        outbox_id INTEGER NOT NULL,
        t         REAL NOT NULL
    );

    CREATE TRIGGER events_outbox AFTER INSERT ON events
    BEGIN INSERT INTO outbox(tbl, row_id) VALUES ('events', NEW.id); END;
    CREATE TRIGGER workpieces_outbox AFTER INSERT ON workpieces
    BEGIN INSERT INTO outbox(tbl, row_id) VALUES ('workpieces', NEW.id); END;
    CREATE TRIGGER inspections_outbox AFTER INSERT ON inspections
    BEGIN INSERT INTO outbox(tbl, row_id) VALUES ('inspections', NEW.id); END;
    CREATE TRIGGER sampling_queue_outbox AFTER INSERT ON sampling_queue
    BEGIN INSERT INTO outbox(tbl, row_id) VALUES ('sampling_queue', NEW.id); END;
    CREATE TRIGGER experiments_outbox AFTER INSERT ON experiments
    BEGIN INSERT INTO outbox(tbl, row_id) VALUES ('experiments', NEW.id); END;

    -- The analyzers record these as events (payloads agreed with them); the
    -- views give them columns without a second copy to keep in step.
    CREATE VIEW chatter_events AS
    SELECT id, uuid, machine_id, t, source, kind,
           json_extract(payload, '$.machine') AS machine,
           json_extract(payload, '$.index') AS chatter_index,
           json_extract(payload, '$.threshold') AS threshold,
           json_extract(payload, '$.chatter_frequency_hz') AS chatter_frequency_hz,
           json_extract(payload, '$.rpm') AS rpm,
           json_extract(payload, '$.depth_mm') AS depth_mm,
           json_extract(payload, '$.tool') AS tool,
           json_extract(payload, '$.material') AS material
    FROM events WHERE kind IN ('chatter_alarm', 'chatter_cleared');
    CREATE VIEW suppression_actions AS
    SELECT id, uuid, machine_id, t, source,
           json_extract(payload, '$.strategy') AS strategy,
           json_extract(payload, '$.rpm_before') AS rpm_before,
           json_extract(payload, '$.rpm_after') AS rpm_after,
           json_extract(payload, '$.index') AS chatter_index,
           json_extract(payload, '$.threshold') AS threshold,
           json_extract(payload, '$.chatter_frequency_hz') AS chatter_frequency_hz,
           json_extract(payload, '$.sent') AS sent,
           json_extract(payload, '$.reason') AS reason
    FROM events WHERE kind = 'suppression_action';
    CREATE VIEW compensations AS
    SELECT id, uuid, machine_id, t, source,
           json_extract(payload, '$.predicted_um') AS predicted_um,
           json_extract(payload, '$.offset_um') AS offset_um,
           json_extract(payload, '$.model') AS model
    FROM events WHERE kind = 'compensation';
    """),
    (3, """
    -- rows a sink's server refused for their content (not for an outage):
    -- set aside so the rows after them still go; kept here, never lost
    CREATE TABLE forward_refused (
        sink      TEXT NOT NULL,
        outbox_id INTEGER NOT NULL,
        tbl       TEXT NOT NULL,
        row_id    INTEGER NOT NULL,
        error     TEXT NOT NULL,
        t         REAL NOT NULL,
        PRIMARY KEY (sink, outbox_id)
    );
    """),
    (4, """
    -- one cut (entry to exit) as suppression saw it: the stability refit's evidence
    CREATE VIEW cuts AS
    SELECT id, uuid, machine_id, t, source,
           json_extract(payload, '$.machine') AS machine,
           json_extract(payload, '$.tool') AS tool,
           json_extract(payload, '$.material') AS material,
           json_extract(payload, '$.start_t') AS start_t,
           json_extract(payload, '$.end_t') AS end_t,
           json_extract(payload, '$.rpm_start') AS rpm_start,
           json_extract(payload, '$.rpm_end') AS rpm_end,
           json_extract(payload, '$.depth_mm') AS depth_mm,
           json_extract(payload, '$.feed_mm_rev') AS feed_mm_rev,
           json_extract(payload, '$.outcome') AS outcome,
           json_extract(payload, '$.first_alarm_s') AS first_alarm_s,
           json_extract(payload, '$.chatter_frequency_hz') AS chatter_frequency_hz,
           json_array_length(payload, '$.actions') AS actions,
           json_extract(payload, '$.cured') AS cured,
           json_extract(payload, '$.model') AS model
    FROM events WHERE kind = 'cut';
    """),
    (5, """
    -- the turret tools that cut each part, in the order they first cut ("1,2"); NULL
    -- where the machine maps no tool_number register
    ALTER TABLE workpieces ADD COLUMN tools TEXT;
    -- alarms and cuts carry the turret tool in their payloads: a column in their views
    DROP VIEW chatter_events;
    CREATE VIEW chatter_events AS
    SELECT id, uuid, machine_id, t, source, kind,
           json_extract(payload, '$.machine') AS machine,
           json_extract(payload, '$.index') AS chatter_index,
           json_extract(payload, '$.threshold') AS threshold,
           json_extract(payload, '$.chatter_frequency_hz') AS chatter_frequency_hz,
           json_extract(payload, '$.rpm') AS rpm,
           json_extract(payload, '$.depth_mm') AS depth_mm,
           json_extract(payload, '$.tool') AS tool,
           json_extract(payload, '$.material') AS material,
           json_extract(payload, '$.tool_number') AS tool_number
    FROM events WHERE kind IN ('chatter_alarm', 'chatter_cleared');
    DROP VIEW cuts;
    CREATE VIEW cuts AS
    SELECT id, uuid, machine_id, t, source,
           json_extract(payload, '$.machine') AS machine,
           json_extract(payload, '$.tool') AS tool,
           json_extract(payload, '$.material') AS material,
           json_extract(payload, '$.start_t') AS start_t,
           json_extract(payload, '$.end_t') AS end_t,
           json_extract(payload, '$.rpm_start') AS rpm_start,
           json_extract(payload, '$.rpm_end') AS rpm_end,
           json_extract(payload, '$.depth_mm') AS depth_mm,
           json_extract(payload, '$.feed_mm_rev') AS feed_mm_rev,
           json_extract(payload, '$.outcome') AS outcome,
           json_extract(payload, '$.first_alarm_s') AS first_alarm_s,
           json_extract(payload, '$.chatter_frequency_hz') AS chatter_frequency_hz,
           json_array_length(payload, '$.actions') AS actions,
           json_extract(payload, '$.cured') AS cured,
           json_extract(payload, '$.model') AS model,
           json_extract(payload, '$.tool_number') AS tool_number
    FROM events WHERE kind = 'cut';
    """),    (6, """
    -- The store's own clock, which retention ages rows by (StoreClock): it runs with
    -- lathed, so a wall clock set ahead does not age every record at once, nor one set
    -- back (an RTC reset at boot) make fresh records look years old.
    CREATE TABLE store_clock (
        id      INTEGER PRIMARY KEY CHECK (id = 1),
        store_t REAL NOT NULL,
        wall_t  REAL NOT NULL
    );
    ALTER TABLE outbox ADD COLUMN age_t REAL;
    UPDATE outbox SET age_t = (SELECT t FROM events WHERE id = outbox.row_id) WHERE tbl = 'events';
    UPDATE outbox SET age_t = (SELECT end_t FROM workpieces WHERE id = outbox.row_id) WHERE tbl = 'workpieces';
    UPDATE outbox SET age_t = (SELECT t FROM inspections WHERE id = outbox.row_id) WHERE tbl = 'inspections';
    UPDATE outbox SET age_t = (SELECT t FROM sampling_queue WHERE id = outbox.row_id) WHERE tbl = 'sampling_queue';
    UPDATE outbox SET age_t = (SELECT t FROM experiments WHERE id = outbox.row_id) WHERE tbl = 'experiments';
    DROP TRIGGER events_outbox;
    CREATE TRIGGER events_outbox AFTER INSERT ON events BEGIN INSERT INTO outbox(tbl, row_id, age_t)
    VALUES ('events', NEW.id, (SELECT store_t FROM store_clock)); END;
    DROP TRIGGER workpieces_outbox;
    CREATE TRIGGER workpieces_outbox AFTER INSERT ON workpieces BEGIN INSERT INTO outbox(tbl, row_id, age_t)
    VALUES ('workpieces', NEW.id, (SELECT store_t FROM store_clock)); END;
    DROP TRIGGER inspections_outbox;
    CREATE TRIGGER inspections_outbox AFTER INSERT ON inspections BEGIN INSERT INTO outbox(tbl, row_id, age_t)
    VALUES ('inspections', NEW.id, (SELECT store_t FROM store_clock)); END;
    DROP TRIGGER sampling_queue_outbox;
    CREATE TRIGGER sampling_queue_outbox AFTER INSERT ON sampling_queue BEGIN INSERT INTO outbox(tbl, row_id, age_t)
    VALUES ('sampling_queue', NEW.id, (SELECT store_t FROM store_clock)); END;
    DROP TRIGGER experiments_outbox;
    CREATE TRIGGER experiments_outbox AFTER INSERT ON experiments BEGIN INSERT INTO outbox(tbl, row_id, age_t)
    VALUES ('experiments', NEW.id, (SELECT store_t FROM store_clock)); END;
    """),
    (7, """
    -- why a part was not watched whole (lathed was not running, the records analyzer
    -- restarting, a counter reset): NULL where it was; outcome 'unobserved': not at all
    ALTER TABLE workpieces ADD COLUMN unwatched TEXT;
    """),
    (8, """
    -- the records analyzer's last reading of each machine's part counter: a step that finished
    -- no part (stepped by hand while idle) is in no part's row, and the next start counted it as
    -- a part made while lathed was down. held: the part the program's stop left was written
    -- aborted at lathed's stop, before the counter stepped for it: that step is the part's own.
    -- run, seq: which records analyzer run saved it, in what order (a retried write's save
    -- never overwrites a later one). Local state, not a record: not forwarded.
    CREATE TABLE last_part_count (
        machine TEXT PRIMARY KEY,
        count   INTEGER NOT NULL,
        t       REAL NOT NULL,
        held    INTEGER NOT NULL,
        run     TEXT NOT NULL,
        seq     INTEGER NOT NULL
    );
    """),
]


def statements(sql: str) -> list[str]:
    """Split a script into statements; a trigger body's ';' does not end one."""
    out, buf = [], ""
    for line in sql.splitlines(keepends=True):
        buf += line
        if sqlite3.complete_statement(buf):
            out.append(buf.strip())
            buf = ""
    if buf.strip():
        raise ValueError(f"incomplete SQL statement: {buf.strip()[:60]}")
    return out


def migrate(con: sqlite3.Connection) -> int:
    version = con.execute("PRAGMA user_version").fetchone()[0]
    for v, sql in MIGRATIONS:
        if v > version:
            con.execute("BEGIN IMMEDIATE")
            try:
                for stmt in statements(sql):
                    con.execute(stmt)
                con.execute(f"PRAGMA user_version={v}")
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise
            version = v
    return version


EVENT_SQL = "INSERT INTO events(uuid, machine_id, t, source, kind, payload) VALUES (?,?,?,?,?,?)"

# Every kind of event lathed and its built-in plugins record (tests/test_store.py reads the code's
# record calls against it, so a new kind cannot be left out). A third-party plugin's kinds are
# known once recorded: event_kinds() adds the store's.
KINDS = frozenset({
    "daemon_started", "daemon_stopped", "stop_waited", "config_reloaded", "config_reload_refused",
    "store_pruned", "forward_refused", "simulator_failed", "command_record_damaged",
    *(f"{c}_{w}" for c in ("machine", "sensor", "analyzer") for w in ("fault", "recovered")),
    "command_sent", "command_refused", "command_failed", "speed_not_released", "override_found_held",
    "implausible_value", "alarm_raised", "alarm_cleared", "alarm_refresh_refused", "mtconnect_gap",
    "part_counter_reset",
    "chatter_alarm", "chatter_cleared", "chatter_blind", "chatter_sight_back", "unusable_vibration_rate", "cut",
    "audio_samples_lost",
    "suppression_action", "suppression_proposed", "suppression_mode", "suppression_exhausted",
    "suppression_advice", "suppression_advice_lifted", "suppression_cures_forgotten", "spindle_not_following",
    "suppression_held",
    "stability_model_adopted", "stability_model_superseded", "stability_model_unreadable",
    "stability_refit_not_adopted", "stability_model_learned", "stability_model_withdrawn",
    "stability_learn_not_trusted",
    "compensation", "thermal_measurement", "thermal_refit", "thermal_touchoff", "thermal_model_unreadable",
    "thermal_held", "thermal_resumed",
    "part_completed", "part_abnormal", "part_unobserved", "part_inspected",
})


def event_kinds(con: sqlite3.Connection) -> set[str]:
    """KINDS and every kind in the store: one index seek per kind, not a scan of the events."""
    rows = con.execute("WITH RECURSIVE k(kind) AS (SELECT min(kind) FROM events UNION ALL "
                       "SELECT (SELECT min(kind) FROM events WHERE kind > k.kind) FROM k WHERE k.kind IS NOT NULL) "
                       "SELECT kind FROM k WHERE kind IS NOT NULL").fetchall()
    return set(KINDS) | {r[0] for r in rows}


def unknown_kind(con: sqlite3.Connection, kinds: list[str], declared: set[str] = frozenset()) -> str | None:
    """Why ``kinds`` cannot narrow events (a misspelt kind matched nothing, and said nothing):
    None when every one is known (``declared``: the loaded plugins' own kinds)."""
    bad = [k for k in kinds if k not in KINDS and k not in declared]
    if not bad:
        return None
    known = event_kinds(con) | declared
    bad = [k for k in bad if k not in known]
    if not bad:
        return None
    near = difflib.get_close_matches(bad[0], known, 1)
    return (f"{bad[0]!r} is not a kind of event{f' (did you mean {near[0]!r}?)' if near else ''}; "
            f"known: {', '.join(sorted(known))}")
