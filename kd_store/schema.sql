-- Long-term memory of the knowledge database, schema version 3 (2 added map_tile_rows;
-- 3 added run_rows and a run_id on every row: one file may hold several runs, each in its
-- own world frame, `wm run --append`).
-- Units: metres, radians, m/s; times int64 nanoseconds (t_ns). Quaternions (qx, qy, qz, qw).
-- cov_pv: the 21 upper-triangle entries, row-major, of the 6x6 covariance over
-- (x, y, z, vx, vy, vz); var_rpy: variances of roll, pitch, yaw (rad^2).
-- Base tables hold the data; notebooks read the views (documented in docs/kd.md).

CREATE TABLE IF NOT EXISTS kd_meta (key VARCHAR NOT NULL, value VARCHAR NOT NULL);

CREATE TABLE IF NOT EXISTS entity_frames (
    id BIGINT NOT NULL,
    name VARCHAR NOT NULL,
    name_uncertainty DOUBLE NOT NULL,
    level TINYINT NOT NULL,
    status VARCHAR NOT NULL,
    confidence DOUBLE NOT NULL,
    generic_classes VARCHAR[] NOT NULL,
    specific_class VARCHAR,
    worth_preserve DOUBLE NOT NULL,
    worth_acquire DOUBLE NOT NULL,
    worth_defend DOUBLE NOT NULL,
    worth_defeat DOUBLE NOT NULL,
    cost DOUBLE NOT NULL,
    risk DOUBLE NOT NULL,
    images VARCHAR[] NOT NULL,
    map_cells STRUCT(map_level INTEGER, col BIGINT, "row" BIGINT)[] NOT NULL,
    attributes MAP(VARCHAR, STRUCT(observed DOUBLE, observed_var DOUBLE, estimated DOUBLE,
                                   estimated_var DOUBLE, predicted DOUBLE, predicted_var DOUBLE))
               NOT NULL,
    created_ns BIGINT NOT NULL,
    noteworthy BOOLEAN NOT NULL,
    t_ns BIGINT,
    frame VARCHAR,
    x DOUBLE, y DOUBLE, z DOUBLE,
    qx DOUBLE, qy DOUBLE, qz DOUBLE, qw DOUBLE,
    vx DOUBLE, vy DOUBLE, vz DOUBLE,
    cov_pv DOUBLE[21],
    var_rpy DOUBLE[3],
    run_id BIGINT NOT NULL DEFAULT 0
);

CREATE TABLE IF NOT EXISTS entity_state_rows (
    entity_id BIGINT NOT NULL,
    t_ns BIGINT NOT NULL,
    frame VARCHAR NOT NULL,
    x DOUBLE NOT NULL, y DOUBLE NOT NULL, z DOUBLE NOT NULL,
    qx DOUBLE NOT NULL, qy DOUBLE NOT NULL, qz DOUBLE NOT NULL, qw DOUBLE NOT NULL,
    vx DOUBLE NOT NULL, vy DOUBLE NOT NULL, vz DOUBLE NOT NULL,
    cov_pv DOUBLE[21] NOT NULL,
    var_rpy DOUBLE[3] NOT NULL,
    run_id BIGINT NOT NULL DEFAULT 0
);

CREATE TABLE IF NOT EXISTS entity_expectation_rows (
    entity_id BIGINT NOT NULL,
    t_ns BIGINT NOT NULL,
    frame VARCHAR NOT NULL,
    x DOUBLE NOT NULL, y DOUBLE NOT NULL, z DOUBLE NOT NULL,
    qx DOUBLE NOT NULL, qy DOUBLE NOT NULL, qz DOUBLE NOT NULL, qw DOUBLE NOT NULL,
    vx DOUBLE NOT NULL, vy DOUBLE NOT NULL, vz DOUBLE NOT NULL,
    cov_pv DOUBLE[21] NOT NULL,
    var_rpy DOUBLE[3] NOT NULL,
    run_id BIGINT NOT NULL DEFAULT 0
);

CREATE TABLE IF NOT EXISTS event_frames (
    id BIGINT NOT NULL,
    name VARCHAR NOT NULL,
    class_name VARCHAR NOT NULL,
    t_start_ns BIGINT NOT NULL,
    t_end_ns BIGINT,
    attributes MAP(VARCHAR, DOUBLE) NOT NULL,
    level TINYINT NOT NULL,
    confidence DOUBLE NOT NULL,
    name_uncertainty DOUBLE NOT NULL,
    worth_preserve DOUBLE NOT NULL,
    worth_acquire DOUBLE NOT NULL,
    worth_defend DOUBLE NOT NULL,
    worth_defeat DOUBLE NOT NULL,
    cost DOUBLE NOT NULL,
    risk DOUBLE NOT NULL,
    noteworthy BOOLEAN NOT NULL,
    run_id BIGINT NOT NULL DEFAULT 0
);

CREATE TABLE IF NOT EXISTS relation_rows (
    src_id BIGINT NOT NULL,
    kind VARCHAR NOT NULL,
    dst_id BIGINT NOT NULL,
    t_from_ns BIGINT NOT NULL,
    t_to_ns BIGINT,
    run_id BIGINT NOT NULL DEFAULT 0
);

CREATE TABLE IF NOT EXISTS class_prototypes (
    name VARCHAR NOT NULL,
    kind VARCHAR NOT NULL,
    level TINYINT NOT NULL,
    is_a VARCHAR,
    attributes MAP(VARCHAR, DOUBLE) NOT NULL,
    weights MAP(VARCHAR, DOUBLE) NOT NULL,
    worth_preserve DOUBLE NOT NULL,
    worth_acquire DOUBLE NOT NULL,
    worth_defend DOUBLE NOT NULL,
    worth_defeat DOUBLE NOT NULL,
    cost DOUBLE NOT NULL,
    risk DOUBLE NOT NULL,
    fitted BOOLEAN NOT NULL DEFAULT false
);

-- One row per layer of a map tile (kd_store/tiles.py); a tile's rows are written together.
-- data: the array's C-order bytes, zlib-compressed; dtype: numpy dtype string ('<f4', ...).
CREATE TABLE IF NOT EXISTS map_tile_rows (
    level VARCHAR NOT NULL,
    tx BIGINT NOT NULL,
    ty BIGINT NOT NULL,
    layer VARCHAR NOT NULL,
    dtype VARCHAR NOT NULL,
    shape INTEGER[] NOT NULL,
    data BLOB NOT NULL,
    t_ns BIGINT NOT NULL,
    run_id BIGINT NOT NULL DEFAULT 0
);

-- One row per run written into this file (kd_store/persist.py begin_run). A run's entities,
-- events, relations and map tiles carry its run_id; ids are unique across runs.
CREATE TABLE IF NOT EXISTS run_rows (
    run_id BIGINT NOT NULL,
    source VARCHAR NOT NULL,
    started_utc TIMESTAMP NOT NULL
);

-- ---------------------------------------------------------------- views for notebooks

CREATE OR REPLACE VIEW entities AS
SELECT id, name, name_uncertainty, level, status, confidence, generic_classes, specific_class,
       coalesce(specific_class, generic_classes[-1]) AS class_name,
       worth_preserve, worth_acquire, worth_defend, worth_defeat, cost, risk,
       images, map_cells, attributes, created_ns, noteworthy,
       t_ns, frame, x, y, z, qx, qy, qz, qw, vx, vy, vz, cov_pv, var_rpy, run_id
FROM entity_frames;

CREATE OR REPLACE VIEW entity_states AS
SELECT entity_id, t_ns, frame, x, y, z, qx, qy, qz, qw, vx, vy, vz, cov_pv, var_rpy, run_id
FROM entity_state_rows;

CREATE OR REPLACE VIEW entity_expectations AS
SELECT entity_id, t_ns, frame, x, y, z, qx, qy, qz, qw, vx, vy, vz, cov_pv, var_rpy, run_id
FROM entity_expectation_rows;

CREATE OR REPLACE VIEW entity_attributes AS
SELECT entity_id, name,
       struct_extract(a, 'observed') AS observed,
       struct_extract(a, 'observed_var') AS observed_var,
       struct_extract(a, 'estimated') AS estimated,
       struct_extract(a, 'estimated_var') AS estimated_var,
       struct_extract(a, 'predicted') AS predicted,
       struct_extract(a, 'predicted_var') AS predicted_var, run_id
FROM (SELECT id AS entity_id, unnest(map_keys(attributes)) AS name,
             unnest(map_values(attributes)) AS a, run_id
      FROM entity_frames);

CREATE OR REPLACE VIEW events AS
SELECT id, name, class_name, t_start_ns, t_end_ns,
       (t_end_ns - t_start_ns) / 1e9 AS duration_s, attributes, level, confidence,
       name_uncertainty, worth_preserve, worth_acquire, worth_defend, worth_defeat, cost, risk,
       noteworthy, run_id
FROM event_frames;

CREATE OR REPLACE VIEW relations AS
SELECT src_id, kind, dst_id, CAST(NULL AS VARCHAR) AS dst_name, t_from_ns, t_to_ns, run_id
FROM relation_rows
UNION ALL
SELECT id, 'is_a', NULL, c, created_ns, NULL, run_id
FROM (SELECT id, created_ns, run_id, unnest(list_concat(generic_classes,
      CASE WHEN specific_class IS NULL THEN [] ELSE [specific_class] END)) AS c
      FROM entity_frames)
UNION ALL
SELECT id, 'appears_in', NULL, img, created_ns, NULL, run_id
FROM (SELECT id, created_ns, run_id, unnest(images) AS img FROM entity_frames);

CREATE OR REPLACE VIEW classes AS
SELECT name, kind, level, is_a, attributes, weights,
       worth_preserve, worth_acquire, worth_defend, worth_defeat, cost, risk, fitted
FROM class_prototypes;

CREATE OR REPLACE VIEW map_tiles AS
SELECT level, tx, ty, layer, dtype, shape, data, octet_length(data) AS stored_bytes, t_ns,
       run_id
FROM map_tile_rows;

CREATE OR REPLACE VIEW runs AS
SELECT r.run_id, r.source, r.started_utc,
       (SELECT count(*) FROM entity_frames f WHERE f.run_id = r.run_id) AS entities,
       (SELECT count(*) FROM event_frames e WHERE e.run_id = r.run_id) AS events
FROM run_rows r;

CREATE OR REPLACE MACRO entity_states_as_of(t) AS TABLE
SELECT * FROM entity_states WHERE t_ns <= t
QUALIFY row_number() OVER (PARTITION BY entity_id ORDER BY t_ns DESC) = 1;

CREATE OR REPLACE MACRO events_at(t) AS TABLE
SELECT * FROM events WHERE t_start_ns <= t AND (t_end_ns IS NULL OR t_end_ns >= t);
