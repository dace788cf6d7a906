//! The dataset's parquet tables, written with parquet's low-level writer (no arrow): the frame
//! table (`data/`, and the staged parts), the episode table (`meta/episodes/`) and the task
//! table (`meta/tasks.parquet`), each with the schema pyarrow gives LeRobot's tables:
//! nullable columns, vectors as 3-level `LIST`s (`list` / `element`), snappy compression.
//!
//! Reading uses parquet's record API: slow per value, and only needed for recovery, resuming a
//! dataset and export, never in the recording loop.

use crate::error::RecordError;
use crate::features::{Features, SCALARS};
use crate::sampler::Frame;
use crate::stats::{FeatureStats, STAT_NAMES};
use parquet::basic::{Compression, ConvertedType, LogicalType, Repetition, Type as Physical};
use parquet::column::writer::{ColumnCloseResult, ColumnWriter};
use parquet::data_type::{ByteArray, ByteArrayType, DoubleType, FloatType, Int64Type};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use parquet::file::reader::{FileReader, SerializedFileReader};
use parquet::file::writer::{SerializedFileWriter, SerializedRowGroupWriter};
use parquet::record::{Field, Row};
use parquet::schema::types::{Type, TypePtr};
use std::collections::HashMap;
use std::fs::File;
use std::path::Path;
use std::sync::Arc;

type PqResult<T> = Result<T, parquet::errors::ParquetError>;

/// One row of the frame table.
#[derive(Debug, Clone, PartialEq)]
pub struct DataRow {
    /// The vector features.
    pub frame: Frame,
    /// `frame_index / fps`, s.
    pub timestamp: f32,
    /// Frame number within the episode.
    pub frame_index: i64,
    /// The episode's index in the dataset.
    pub episode_index: i64,
    /// Frame number within the dataset.
    pub index: i64,
    /// The task's index (`meta/tasks.parquet`).
    pub task_index: i64,
}

fn optional(name: &str, physical: Physical, logical: Option<LogicalType>) -> PqResult<TypePtr> {
    Ok(Arc::new(
        Type::primitive_type_builder(name, physical)
            .with_repetition(Repetition::OPTIONAL)
            .with_logical_type(logical)
            .build()?,
    ))
}

/// A nullable list of nullable `physical` (pyarrow's layout for `list<element: T>`).
fn list(name: &str, physical: Physical, logical: Option<LogicalType>) -> PqResult<TypePtr> {
    list_of(name, optional("element", physical, logical)?)
}

/// `depth` nested nullable lists of nullable `physical` (`list<list<list<double>>>` for an
/// image's statistics, shaped `[3, 1, 1]`).
fn nested_list(name: &str, depth: usize, physical: Physical) -> PqResult<TypePtr> {
    if depth <= 1 {
        return list(name, physical, None);
    }
    list_of(name, nested_list("element", depth - 1, physical)?)
}

/// A nullable `LIST` group named `name` of `element`s.
fn list_of(name: &str, element: TypePtr) -> PqResult<TypePtr> {
    let repeated = Type::group_type_builder("list")
        .with_repetition(Repetition::REPEATED)
        .with_fields(vec![element])
        .build()?;
    Ok(Arc::new(
        Type::group_type_builder(name)
            .with_repetition(Repetition::OPTIONAL)
            .with_logical_type(Some(LogicalType::List))
            .with_converted_type(ConvertedType::LIST)
            .with_fields(vec![Arc::new(repeated)])
            .build()?,
    ))
}

fn message(fields: Vec<TypePtr>) -> PqResult<TypePtr> {
    Ok(Arc::new(
        Type::group_type_builder("schema")
            .with_fields(fields)
            .build()?,
    ))
}

fn string() -> Option<LogicalType> {
    Some(LogicalType::String)
}

/// The frame table's schema: vector features as `list<float>`, then LeRobot's scalars. A
/// feature of shape `[1]` (one gripper's force) is a plain float column: LeRobot's
/// `get_hf_features_from_features` maps shape `(1,)` to a scalar `Value`, and its loader could
/// not cast a list to it.
pub fn data_schema(features: &Features) -> PqResult<TypePtr> {
    let mut fields = Vec::new();
    for v in features.vectors() {
        if features.width(v) == 1 {
            fields.push(optional(v.key(), Physical::FLOAT, None)?);
        } else {
            fields.push(list(v.key(), Physical::FLOAT, None)?);
        }
    }
    for (key, dtype) in SCALARS {
        let physical = if dtype == "float32" {
            Physical::FLOAT
        } else {
            Physical::INT64
        };
        fields.push(optional(key, physical, None)?);
    }
    message(fields)
}

/// The `huggingface` schema metadata the `datasets` library writes beside a table: the features
/// as `Sequence(Value(float32), length)` and `Value`, so a reader restores fixed-length vectors.
pub fn huggingface_metadata(features: &Features) -> String {
    let mut map = serde_json::Map::new();
    for v in features.vectors() {
        let spec = if features.width(v) == 1 {
            serde_json::json!({"dtype": "float32", "_type": "Value"})
        } else {
            serde_json::json!({"feature": {"dtype": "float32", "_type": "Value"}, "length": features.width(v), "_type": "Sequence"})
        };
        map.insert(v.key().into(), spec);
    }
    for (key, dtype) in SCALARS {
        map.insert(
            key.into(),
            serde_json::json!({"dtype": dtype, "_type": "Value"}),
        );
    }
    serde_json::json!({"info": {"features": map}}).to_string()
}

/// The Arrow types of the frame table's columns, in order (what `ARROW:schema` says).
pub fn data_arrow_schema(features: &Features) -> String {
    use crate::arrow_schema::{arrow_schema, ArrowType};
    let mut columns: Vec<(&str, ArrowType)> = features
        .vectors()
        .into_iter()
        .map(|v| {
            let t = match features.width(v) {
                1 => ArrowType::Float32,
                n => ArrowType::Float32List(n as i32),
            };
            (v.key(), t)
        })
        .collect();
    for (key, dtype) in SCALARS {
        let t = if dtype == "float32" {
            ArrowType::Float32
        } else {
            ArrowType::Int64
        };
        columns.push((key, t));
    }
    arrow_schema(&columns)
}

/// The schema metadata of a data file: Hugging Face's features and the Arrow schema, as a
/// file LeRobot writes carries them.
pub fn data_metadata(features: &Features) -> Vec<(String, String)> {
    vec![
        ("huggingface".into(), huggingface_metadata(features)),
        ("ARROW:schema".into(), data_arrow_schema(features)),
    ]
}

/// Writer properties: snappy (as LeRobot), with the given schema metadata.
pub fn properties(metadata: Vec<(String, String)>) -> Arc<WriterProperties> {
    let kv = metadata
        .into_iter()
        .map(|(k, v)| KeyValue::new(k, v))
        .collect::<Vec<_>>();
    Arc::new(
        WriterProperties::builder()
            .set_compression(Compression::SNAPPY)
            .set_key_value_metadata(Some(kv))
            .build(),
    )
}

/// Definition/repetition levels of `rows` lists of `width` non-null elements each.
fn list_levels(rows: usize, width: usize) -> (Vec<i16>, Vec<i16>) {
    let def = vec![3i16; rows * width];
    let mut rep = vec![1i16; rows * width];
    for r in 0..rows {
        rep[r * width] = 0;
    }
    (def, rep)
}

fn write_f32_list(
    col: &mut ColumnWriter<'_>,
    values: &[f32],
    rows: usize,
    width: usize,
) -> PqResult<()> {
    let (def, rep) = list_levels(rows, width);
    match col {
        ColumnWriter::FloatColumnWriter(w) => {
            w.write_batch(values, Some(&def), Some(&rep)).map(|_| ())
        }
        _ => Err(parquet::errors::ParquetError::General(
            "expected a float column".into(),
        )),
    }
}

/// Appends one row group of `rows` to `writer` (whose schema is [`data_schema`]).
pub fn write_data_rows<W: std::io::Write + Send>(
    writer: &mut SerializedFileWriter<W>,
    features: &Features,
    rows: &[DataRow],
) -> PqResult<()> {
    let mut rg = writer.next_row_group()?;
    for v in features.vectors() {
        let width = features.width(v);
        let mut values = Vec::with_capacity(rows.len() * width);
        for r in rows {
            let x = r.frame.vector(v);
            if x.len() != width {
                return Err(parquet::errors::ParquetError::General(format!(
                    "{}: a frame has {} values, the feature {width}",
                    v.key(),
                    x.len()
                )));
            }
            values.extend_from_slice(x);
        }
        let mut col = rg.next_column()?.ok_or_else(|| {
            parquet::errors::ParquetError::General("schema has fewer columns".into())
        })?;
        if width == 1 {
            let def = vec![1i16; rows.len()];
            col.typed::<FloatType>()
                .write_batch(&values, Some(&def), None)?;
        } else {
            write_f32_list(col.untyped(), &values, rows.len(), width)?;
        }
        col.close()?;
    }
    let def = vec![1i16; rows.len()];
    for (key, _) in SCALARS {
        if key == "timestamp" {
            let t: Vec<f32> = rows.iter().map(|r| r.timestamp).collect();
            write_column::<FloatType, W>(&mut rg, &t, &def, None)?;
        } else {
            let x: Vec<i64> = rows
                .iter()
                .map(|r| match key {
                    "frame_index" => r.frame_index,
                    "episode_index" => r.episode_index,
                    "index" => r.index,
                    _ => r.task_index,
                })
                .collect();
            write_column::<Int64Type, W>(&mut rg, &x, &def, None)?;
        }
    }
    rg.close()?;
    Ok(())
}

/// Copies the first `row_groups` row groups of `source` into `writer` as encoded bytes (no
/// decoding): appending an episode to a data file rewrites the file without re-encoding it.
pub fn copy_row_groups<W: std::io::Write + Send>(
    writer: &mut SerializedFileWriter<W>,
    source: &File,
    row_groups: usize,
) -> PqResult<()> {
    let reader = SerializedFileReader::new(source.try_clone()?)?;
    let metadata = reader.metadata();
    for rg in metadata.row_groups().iter().take(row_groups) {
        let mut out = writer.next_row_group()?;
        for column in rg.columns() {
            let close = ColumnCloseResult {
                bytes_written: column.compressed_size() as u64,
                rows_written: rg.num_rows() as u64,
                metadata: column.clone(),
                bloom_filter: None,
                column_index: None,
                offset_index: None,
            };
            out.append_column(source, close)?;
        }
        out.close()?;
    }
    Ok(())
}

/// Rows per row group of a parquet file, and its schema.
pub fn row_groups(path: &Path) -> Result<(Vec<i64>, TypePtr), RecordError> {
    let file = File::open(path).map_err(RecordError::io(path, "opening"))?;
    let reader = SerializedFileReader::new(file).map_err(RecordError::parquet(path))?;
    let m = reader.metadata();
    Ok((
        m.row_groups().iter().map(|rg| rg.num_rows()).collect(),
        m.file_metadata().schema_descr().root_schema_ptr(),
    ))
}

fn rows_of(path: &Path) -> Result<Vec<Row>, RecordError> {
    let file = File::open(path).map_err(RecordError::io(path, "opening"))?;
    let reader = SerializedFileReader::new(file).map_err(RecordError::parquet(path))?;
    reader
        .into_iter()
        .collect::<PqResult<Vec<Row>>>()
        .map_err(RecordError::parquet(path))
}

fn columns(row: &Row) -> HashMap<&str, &Field> {
    row.get_column_iter()
        .map(|(k, v)| (k.as_str(), v))
        .collect()
}

fn want<'a>(
    path: &Path,
    cols: &HashMap<&str, &'a Field>,
    key: &str,
) -> Result<&'a Field, RecordError> {
    cols.get(key)
        .copied()
        .ok_or_else(|| RecordError::invalid(path, format!("no column {key:?}")))
}

fn as_i64(path: &Path, key: &str, f: &Field) -> Result<i64, RecordError> {
    match f {
        Field::Long(v) => Ok(*v),
        Field::Int(v) => Ok(i64::from(*v)),
        other => Err(RecordError::invalid(
            path,
            format!("column {key:?}: {other:?} is not an integer"),
        )),
    }
}

fn as_f64_list(path: &Path, key: &str, f: &Field) -> Result<Vec<f64>, RecordError> {
    // A feature of shape [1] is a scalar column (see `data_schema`).
    match f {
        Field::Float(v) => return Ok(vec![f64::from(*v)]),
        Field::Double(v) => return Ok(vec![*v]),
        _ => {}
    }
    let Field::ListInternal(list) = f else {
        return Err(RecordError::invalid(
            path,
            format!("column {key:?} is not a list"),
        ));
    };
    let mut out = Vec::new();
    for e in list.elements() {
        match e {
            Field::Float(v) => out.push(f64::from(*v)),
            Field::Double(v) => out.push(*v),
            Field::Long(v) => out.push(*v as f64),
            Field::Null => out.push(f64::NAN),
            // An image's statistics nest one value per channel as `[[v]]`.
            nested @ Field::ListInternal(_) => out.extend(as_f64_list(path, key, nested)?),
            other => {
                return Err(RecordError::invalid(
                    path,
                    format!("column {key:?}: element {other:?}"),
                ))
            }
        }
    }
    Ok(out)
}

/// Reads every row of a frame table (a data file or a staged part) for `features`.
pub fn read_data(path: &Path, features: &Features) -> Result<Vec<DataRow>, RecordError> {
    let mut out = Vec::new();
    for row in rows_of(path)? {
        let cols = columns(&row);
        let mut frame = Frame::missing(features);
        for v in features.vectors() {
            let x = as_f64_list(path, v.key(), want(path, &cols, v.key())?)?;
            if x.len() != features.width(v) {
                return Err(RecordError::invalid(
                    path,
                    format!(
                        "{}: {} values, the dataset's feature has {}",
                        v.key(),
                        x.len(),
                        features.width(v)
                    ),
                ));
            }
            *frame.vector_mut(v) = x.into_iter().map(|x| x as f32).collect();
        }
        let timestamp = match want(path, &cols, "timestamp")? {
            Field::Float(t) => *t,
            Field::Double(t) => *t as f32,
            other => return Err(RecordError::invalid(path, format!("timestamp {other:?}"))),
        };
        let int = |k: &str| as_i64(path, k, want(path, &cols, k)?);
        out.push(DataRow {
            frame,
            timestamp,
            frame_index: int("frame_index")?,
            episode_index: int("episode_index")?,
            index: int("index")?,
            task_index: int("task_index")?,
        });
    }
    Ok(out)
}

/// One row of the episode table (`meta/episodes/chunk-*/file-*.parquet`).
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeRow {
    /// The episode's index in the dataset.
    pub episode_index: i64,
    /// Its tasks (one: a recorder episode has one task).
    pub tasks: Vec<String>,
    /// Frames in the episode.
    pub length: i64,
    /// Data file chunk.
    pub data_chunk_index: i64,
    /// Data file index within the chunk.
    pub data_file_index: i64,
    /// First dataset index.
    pub dataset_from_index: i64,
    /// One past the last dataset index.
    pub dataset_to_index: i64,
    /// Where each camera's frames of the episode are, in [`Features::cameras`] order.
    pub videos: Vec<VideoSpan>,
    /// Statistics per feature key, in feature order.
    pub stats: Vec<(String, FeatureStats)>,
    /// Episode file chunk.
    pub meta_chunk_index: i64,
    /// Episode file index within the chunk.
    pub meta_file_index: i64,
}

/// Where an episode's frames of one camera are: a video file, and the time span in it (frame
/// `k` of the episode at `from_timestamp + k / fps`).
#[derive(Debug, Clone, PartialEq)]
pub struct VideoSpan {
    /// Video file chunk.
    pub chunk_index: i64,
    /// Video file index within the chunk.
    pub file_index: i64,
    /// The episode's first frame, s into the file.
    pub from_timestamp: f64,
    /// One frame past its last, s.
    pub to_timestamp: f64,
}

/// The episode table's columns of the video of `key`, in LeRobot's names.
fn video_columns(key: &str) -> [String; 4] {
    [
        format!("videos/{key}/chunk_index"),
        format!("videos/{key}/file_index"),
        format!("videos/{key}/from_timestamp"),
        format!("videos/{key}/to_timestamp"),
    ]
}

fn episodes_schema(features: &Features) -> PqResult<TypePtr> {
    let mut fields = vec![
        optional("episode_index", Physical::INT64, None)?,
        list("tasks", Physical::BYTE_ARRAY, string())?,
    ];
    for k in [
        "length",
        "data/chunk_index",
        "data/file_index",
        "dataset_from_index",
        "dataset_to_index",
    ] {
        fields.push(optional(k, Physical::INT64, None)?);
    }
    for camera in &features.cameras {
        let [chunk, file, from, to] = video_columns(&camera.key());
        fields.push(optional(&chunk, Physical::INT64, None)?);
        fields.push(optional(&file, Physical::INT64, None)?);
        fields.push(optional(&from, Physical::DOUBLE, None)?);
        fields.push(optional(&to, Physical::DOUBLE, None)?);
    }
    for key in features.keys() {
        for stat in STAT_NAMES {
            let name = format!("stats/{key}/{stat}");
            fields.push(if stat == "count" {
                list(&name, Physical::INT64, None)?
            } else if features.is_video(&key) {
                nested_list(&name, 3, Physical::DOUBLE)?
            } else {
                list(&name, Physical::DOUBLE, None)?
            });
        }
    }
    fields.push(optional(
        "meta/episodes/chunk_index",
        Physical::INT64,
        None,
    )?);
    fields.push(optional("meta/episodes/file_index", Physical::INT64, None)?);
    message(fields)
}

/// Writes the next column of `rg`, of parquet type `T`, with its levels.
fn write_column<T: parquet::data_type::DataType, W: std::io::Write + Send>(
    rg: &mut SerializedRowGroupWriter<'_, W>,
    values: &[T::T],
    def: &[i16],
    rep: Option<&[i16]>,
) -> PqResult<()> {
    let mut col = rg
        .next_column()?
        .ok_or_else(|| parquet::errors::ParquetError::General("schema has fewer columns".into()))?;
    col.typed::<T>().write_batch(values, Some(def), rep)?;
    col.close()?;
    Ok(())
}

/// Writes the episode table `rows` (their stats in `features` order).
pub fn write_episodes<W: std::io::Write + Send>(
    out: W,
    features: &Features,
    rows: &[EpisodeRow],
) -> PqResult<()> {
    let schema = episodes_schema(features)?;
    let mut writer = SerializedFileWriter::new(out, schema, properties(Vec::new()))?;
    let mut rg = writer.next_row_group()?;
    let def1 = vec![1i16; rows.len()];
    let ints = |f: fn(&EpisodeRow) -> i64| rows.iter().map(f).collect::<Vec<i64>>();
    let int_column = |rg: &mut SerializedRowGroupWriter<'_, W>, x: Vec<i64>| {
        write_column::<Int64Type, W>(rg, &x, &def1, None)
    };
    int_column(&mut rg, ints(|r| r.episode_index))?;
    let (mut tasks, mut def, mut rep) = (Vec::new(), Vec::new(), Vec::new());
    for r in rows {
        for (i, t) in r.tasks.iter().enumerate() {
            tasks.push(ByteArray::from(t.as_str()));
            def.push(3);
            rep.push(i16::from(i > 0));
        }
        if r.tasks.is_empty() {
            def.push(1);
            rep.push(0);
        }
    }
    write_column::<ByteArrayType, W>(&mut rg, &tasks, &def, Some(&rep))?;
    int_column(&mut rg, ints(|r| r.length))?;
    int_column(&mut rg, ints(|r| r.data_chunk_index))?;
    int_column(&mut rg, ints(|r| r.data_file_index))?;
    int_column(&mut rg, ints(|r| r.dataset_from_index))?;
    int_column(&mut rg, ints(|r| r.dataset_to_index))?;
    for (c, camera) in features.cameras.iter().enumerate() {
        let span = |r: &EpisodeRow| {
            r.videos.get(c).cloned().ok_or_else(|| {
                parquet::errors::ParquetError::General(format!(
                    "episode {} has no video of {}",
                    r.episode_index, camera.name
                ))
            })
        };
        let spans = rows.iter().map(span).collect::<PqResult<Vec<_>>>()?;
        int_column(&mut rg, spans.iter().map(|s| s.chunk_index).collect())?;
        int_column(&mut rg, spans.iter().map(|s| s.file_index).collect())?;
        let from: Vec<f64> = spans.iter().map(|s| s.from_timestamp).collect();
        let to: Vec<f64> = spans.iter().map(|s| s.to_timestamp).collect();
        write_column::<DoubleType, W>(&mut rg, &from, &def1, None)?;
        write_column::<DoubleType, W>(&mut rg, &to, &def1, None)?;
    }
    for key in features.keys() {
        for stat in STAT_NAMES {
            write_stat_column(&mut rg, rows, &key, stat, features.is_video(&key))?;
        }
    }
    int_column(&mut rg, ints(|r| r.meta_chunk_index))?;
    int_column(&mut rg, ints(|r| r.meta_file_index))?;
    rg.close()?;
    writer.close()?;
    Ok(())
}

/// The column `stats/<key>/<stat>` of the episode table: one list per episode (a list of
/// one-element lists per channel for an image's statistics other than the count).
fn write_stat_column<W: std::io::Write + Send>(
    rg: &mut SerializedRowGroupWriter<'_, W>,
    rows: &[EpisodeRow],
    key: &str,
    stat: &str,
    image: bool,
) -> PqResult<()> {
    let mut values = Vec::new();
    let mut width = None;
    for r in rows {
        let s = r
            .stats
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, s)| s)
            .ok_or_else(|| {
                parquet::errors::ParquetError::General(format!(
                    "episode {} has no stats for {key}",
                    r.episode_index
                ))
            })?;
        let x = s.get(stat).unwrap_or_default();
        if *width.get_or_insert(x.len()) != x.len() {
            return Err(parquet::errors::ParquetError::General(format!(
                "stats/{key}/{stat}: widths differ"
            )));
        }
        values.extend(x);
    }
    let (n, w) = (rows.len(), width.unwrap_or(0));
    let (def, rep) = if image && stat != "count" {
        // `[[v]]` per channel: a new channel repeats at the outer level (1), every value is
        // fully defined (7: three optional lists, three repeated levels and the optional
        // element).
        let mut rep = vec![1i16; n * w];
        for r in 0..n {
            rep[r * w] = 0;
        }
        (vec![7i16; n * w], rep)
    } else {
        list_levels(n, w)
    };
    if stat == "count" {
        let v: Vec<i64> = values.iter().map(|x| *x as i64).collect();
        write_column::<Int64Type, W>(rg, &v, &def, Some(&rep))
    } else {
        write_column::<DoubleType, W>(rg, &values, &def, Some(&rep))
    }
}

/// Reads an episode table written for `features`.
pub fn read_episodes(path: &Path, features: &Features) -> Result<Vec<EpisodeRow>, RecordError> {
    let mut out = Vec::new();
    for row in rows_of(path)? {
        let cols = columns(&row);
        let int = |k: &str| as_i64(path, k, want(path, &cols, k)?);
        let tasks = match want(path, &cols, "tasks")? {
            Field::ListInternal(l) => l
                .elements()
                .iter()
                .filter_map(|e| match e {
                    Field::Str(s) => Some(s.clone()),
                    _ => None,
                })
                .collect(),
            _ => return Err(RecordError::invalid(path, "tasks is not a list")),
        };
        let mut videos = Vec::new();
        for camera in &features.cameras {
            let [chunk, file, from, to] = video_columns(&camera.key());
            let time = |k: &str| match want(path, &cols, k)? {
                Field::Double(v) => Ok(*v),
                other => Err(RecordError::invalid(
                    path,
                    format!("column {k:?}: {other:?} is not a time"),
                )),
            };
            videos.push(VideoSpan {
                chunk_index: int(&chunk)?,
                file_index: int(&file)?,
                from_timestamp: time(&from)?,
                to_timestamp: time(&to)?,
            });
        }
        let mut stats = Vec::new();
        for key in features.keys() {
            let mut failure = None;
            let s = FeatureStats::from_named(|stat| {
                let name = format!("stats/{key}/{stat}");
                match cols.get(name.as_str()).map(|f| as_f64_list(path, &name, f)) {
                    Some(Ok(v)) => Some(v),
                    Some(Err(e)) => {
                        failure = Some(e.to_string());
                        None
                    }
                    None => None,
                }
            })
            .ok_or_else(|| {
                RecordError::invalid(
                    path,
                    format!(
                        "stats of {key} missing or misshapen{}",
                        failure.map(|f| format!(" ({f})")).unwrap_or_default()
                    ),
                )
            })?;
            stats.push((key, s));
        }
        out.push(EpisodeRow {
            episode_index: int("episode_index")?,
            tasks,
            length: int("length")?,
            data_chunk_index: int("data/chunk_index")?,
            data_file_index: int("data/file_index")?,
            dataset_from_index: int("dataset_from_index")?,
            dataset_to_index: int("dataset_to_index")?,
            videos,
            stats,
            meta_chunk_index: int("meta/episodes/chunk_index")?,
            meta_file_index: int("meta/episodes/file_index")?,
        });
    }
    Ok(out)
}

/// The `pandas` schema metadata that makes `pandas.read_parquet` restore the task text as the
/// frame's index named `task`, as LeRobot's `tasks.to_parquet` leaves it
/// (`pd.Index(tasks, name="task")`; it reads `tasks.loc[text].task_index`).
fn pandas_tasks_metadata() -> String {
    serde_json::json!({
        "index_columns": ["task"],
        "column_indexes": [{"name": null, "field_name": null, "pandas_type": "unicode", "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64", "metadata": null},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": null}
        ],
        "creator": {"library": "nori-recorder", "version": env!("CARGO_PKG_VERSION")},
        "pandas_version": "2.2.0"
    })
    .to_string()
}

/// Writes the task table: `task_index`, and the task text as the pandas index column.
pub fn write_tasks<W: std::io::Write + Send>(out: W, tasks: &[String]) -> PqResult<()> {
    let schema = message(vec![
        optional("task_index", Physical::INT64, None)?,
        optional("task", Physical::BYTE_ARRAY, string())?,
    ])?;
    let props = properties(vec![("pandas".into(), pandas_tasks_metadata())]);
    let mut writer = SerializedFileWriter::new(out, schema, props)?;
    let mut rg = writer.next_row_group()?;
    let def = vec![1i16; tasks.len()];
    let idx: Vec<i64> = (0..tasks.len() as i64).collect();
    let text: Vec<ByteArray> = tasks.iter().map(|t| ByteArray::from(t.as_str())).collect();
    write_column::<Int64Type, W>(&mut rg, &idx, &def, None)?;
    write_column::<ByteArrayType, W>(&mut rg, &text, &def, None)?;
    rg.close()?;
    writer.close()?;
    Ok(())
}

/// Reads the task table: the texts in `task_index` order.
pub fn read_tasks(path: &Path) -> Result<Vec<String>, RecordError> {
    let mut tasks: Vec<(i64, String)> = Vec::new();
    for row in rows_of(path)? {
        let cols = columns(&row);
        let i = as_i64(path, "task_index", want(path, &cols, "task_index")?)?;
        let text =
            // `__index_level_0__`: the unnamed index this recorder wrote before.
            match want(path, &cols, "task").or_else(|_| want(path, &cols, "__index_level_0__"))? {
                Field::Str(s) => s.clone(),
                other => return Err(RecordError::invalid(path, format!("task text {other:?}"))),
            };
        tasks.push((i, text));
    }
    tasks.sort_by_key(|(i, _)| *i);
    for (expected, (i, _)) in tasks.iter().enumerate() {
        if *i != expected as i64 {
            return Err(RecordError::invalid(
                path,
                format!("task indices are not 0..{}", tasks.len()),
            ));
        }
    }
    Ok(tasks.into_iter().map(|(_, t)| t).collect())
}
