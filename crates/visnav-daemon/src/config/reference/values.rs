//! The defaults of the sections whose types do not implement `Serialize`, as TOML: each field
//! read from the value the `Default` impl (or constructor) gives, destructured exhaustively so
//! that a new field does not compile until it is written here, and each enum spelled as its
//! serde name (a test parses the table back to the same value).

use toml::{Table, Value};

use visnav_io::frames::{FramesConfig, PixelFormat, SourceKind, StampMode};
use visnav_link::config::{LinkConfig, OnLost, OutputConfig, OutputMode, StreamRates};

use crate::config::vision::{VisionBackend, VisionConfig};

fn put(t: &mut Table, key: &str, v: impl Into<Value>) {
    t.insert(key.into(), v.into());
}

fn put_opt<V: Into<Value>>(t: &mut Table, key: &str, v: Option<V>) {
    if let Some(v) = v {
        put(t, key, v);
    }
}

fn path_text(p: &std::path::Path) -> String {
    p.to_string_lossy().into_owned()
}

/// `[link]` (its `connection` as given; `signing` absent unless set).
pub fn link(c: &LinkConfig) -> Value {
    let LinkConfig {
        connection,
        system_id,
        component_id,
        autopilot_system_id,
        autopilot_component_id,
        heartbeat_hz,
        heartbeat_timeout_s,
        reconnect_min_s,
        reconnect_max_s,
        timesync_hz,
        timesync_max_rtt_ms,
        streams,
        signing,
        tlog,
        metrics_listen,
    } = c;
    let mut t = Table::new();
    put(&mut t, "connection", connection.as_str());
    put_opt(&mut t, "system_id", system_id.map(i64::from));
    put(&mut t, "component_id", i64::from(*component_id));
    put_opt(
        &mut t,
        "autopilot_system_id",
        autopilot_system_id.map(i64::from),
    );
    put(
        &mut t,
        "autopilot_component_id",
        i64::from(*autopilot_component_id),
    );
    put(&mut t, "heartbeat_hz", *heartbeat_hz);
    put(&mut t, "heartbeat_timeout_s", *heartbeat_timeout_s);
    put(&mut t, "reconnect_min_s", *reconnect_min_s);
    put(&mut t, "reconnect_max_s", *reconnect_max_s);
    put(&mut t, "timesync_hz", *timesync_hz);
    put(&mut t, "timesync_max_rtt_ms", *timesync_max_rtt_ms);
    put(&mut t, "streams", stream_rates(streams));
    if let Some(s) = signing {
        let visnav_link::config::SigningSettings {
            key_file,
            sign_outgoing,
            reject_unsigned,
            link_id,
        } = s;
        let mut st = Table::new();
        put(&mut st, "key_file", path_text(key_file));
        put(&mut st, "sign_outgoing", *sign_outgoing);
        put(&mut st, "reject_unsigned", *reject_unsigned);
        put(&mut st, "link_id", i64::from(*link_id));
        put(&mut t, "signing", st);
    }
    put_opt(&mut t, "tlog", tlog.as_deref().map(path_text));
    put_opt(&mut t, "metrics_listen", metrics_listen.clone());
    Value::Table(t)
}

fn stream_rates(s: &StreamRates) -> Value {
    let StreamRates {
        attitude_hz,
        imu_hz,
        scaled_imu_hz,
        global_position_hz,
        gps_raw_hz,
        system_time_hz,
        pressure_hz,
        min_rate_fraction,
    } = s;
    let mut t = Table::new();
    put(&mut t, "attitude_hz", *attitude_hz);
    put(&mut t, "imu_hz", *imu_hz);
    put_opt(&mut t, "scaled_imu_hz", *scaled_imu_hz);
    put(&mut t, "global_position_hz", *global_position_hz);
    put(&mut t, "gps_raw_hz", *gps_raw_hz);
    put(&mut t, "system_time_hz", *system_time_hz);
    put(&mut t, "pressure_hz", *pressure_hz);
    put(&mut t, "min_rate_fraction", *min_rate_fraction);
    Value::Table(t)
}

/// `[output]`.
pub fn output(c: &OutputConfig) -> Value {
    let OutputConfig {
        modes,
        rate_hz,
        gps_id,
        gps_satellites,
        gps_yaw,
        max_age_s,
        on_lost,
        set_origin,
        sensor_id,
    } = c;
    let mut t = Table::new();
    let modes: Vec<Value> = modes
        .iter()
        .map(|m| {
            Value::from(match m {
                OutputMode::GpsInput => "gps_input",
                OutputMode::VisionPositionEstimate => "vision_position_estimate",
                OutputMode::Odometry => "odometry",
                OutputMode::GlobalPositionSensor => "global_position_sensor",
            })
        })
        .collect();
    put(&mut t, "modes", modes);
    put(&mut t, "rate_hz", *rate_hz);
    put(&mut t, "gps_id", i64::from(*gps_id));
    put(&mut t, "gps_satellites", i64::from(*gps_satellites));
    put(&mut t, "gps_yaw", *gps_yaw);
    put(&mut t, "max_age_s", *max_age_s);
    put(
        &mut t,
        "on_lost",
        match on_lost {
            OnLost::Stop => "stop",
            OnLost::NoFix => "no_fix",
        },
    );
    put(&mut t, "set_origin", *set_origin);
    put(&mut t, "sensor_id", i64::from(*sensor_id));
    Value::Table(t)
}

/// `[frames]`.
pub fn frames(c: &FramesConfig) -> Value {
    let FramesConfig {
        source,
        path,
        command,
        pipeline,
        timeout_s,
        latency_s,
        width_px,
        height_px,
        pixel_format,
        stamp,
        realtime,
        rate_hz,
        max_age_s,
        workers,
    } = c;
    let count = |n: usize| i64::try_from(n).unwrap_or(i64::MAX);
    let mut t = Table::new();
    put(
        &mut t,
        "source",
        match source {
            SourceKind::Directory => "directory",
            SourceKind::Y4m => "y4m",
            SourceKind::Command => "command",
            SourceKind::Gstreamer => "gstreamer",
            SourceKind::V4l2 => "v4l2",
        },
    );
    put(&mut t, "path", path_text(path));
    put(&mut t, "command", command.clone());
    put_opt(&mut t, "pipeline", pipeline.clone());
    put(&mut t, "timeout_s", *timeout_s);
    put(&mut t, "latency_s", *latency_s);
    put_opt(&mut t, "width_px", width_px.map(count));
    put_opt(&mut t, "height_px", height_px.map(count));
    put(
        &mut t,
        "pixel_format",
        match pixel_format {
            PixelFormat::Grey => "GREY",
            PixelFormat::Yuyv => "YUYV",
            PixelFormat::Mjpg => "MJPG",
        },
    );
    put(
        &mut t,
        "stamp",
        match stamp {
            StampMode::Arrival => "arrival",
            StampMode::Source => "source",
        },
    );
    put(&mut t, "realtime", *realtime);
    put_opt(&mut t, "rate_hz", *rate_hz);
    put(&mut t, "max_age_s", *max_age_s);
    put(&mut t, "workers", count(*workers));
    Value::Table(t)
}

/// `[vision]`.
pub fn vision(c: &VisionConfig) -> Value {
    let VisionConfig { backend } = c;
    let mut t = Table::new();
    put(
        &mut t,
        "backend",
        match backend {
            VisionBackend::Cpu => "cpu",
            VisionBackend::Gpu => "gpu",
            VisionBackend::Auto => "auto",
        },
    );
    Value::Table(t)
}
