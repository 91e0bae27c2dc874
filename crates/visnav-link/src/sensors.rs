//! The autopilot's sensor telemetry as typed readings: what the navigation needs of a MAVLink
//! message, in SI units, with its own timestamp, so nothing past the link decodes MAVLink.
//!
//! | message | reading |
//! | --- | --- |
//! | HEARTBEAT | [`Sensor::Heartbeat`]: which autopilot, whether the vehicle flies on rotors |
//! | HIGHRES_IMU | [`Sensor::Imu`], [`ImuSource::Highres`]: SI values as sent, `time_usec` |
//! | SCALED_IMU | [`Sensor::Imu`], [`ImuSource::Scaled`]: mG and mrad/s to SI, `time_boot_ms`; the 16-bit counts kept ([`ImuReading::counts`]) |
//! | RAW_IMU | [`Sensor::Imu`], [`ImuSource::Raw`]: ArduPilot fills it with the same mG / mrad/s, `time_usec` |
//! | ATTITUDE | [`Sensor::Attitude`]: roll, pitch, yaw (ZYX, `R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)`) and body rates |
//! | GPS_RAW_INT, GPS2_RAW | [`Sensor::Gps`] (receiver 1 or 2): degrees, AMSL metres, the accuracies when stated |
//! | SCALED_PRESSURE | [`Sensor::Baro`]: absolute pressure, hPa |
//!
//! A value the message marks unknown (`UINT16_MAX` speed or course, a zero accuracy) is `None`;
//! a non-finite float is passed as it is (the consumer refuses it and counts why).

use mavlink::dialects::ardupilotmega::{GpsFixType, MavAutopilot, MavMessage, MavType};

/// Standard gravity, the unit of the 16-bit IMU messages' mG.
pub const G0_M_S2: f64 = 9.806_65;

/// One sensor reading from the autopilot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Sensor {
    /// The vehicle's HEARTBEAT.
    Heartbeat {
        /// Which autopilot sent it.
        autopilot: Autopilot,
        /// Quad/hexa/octo/tri/coaxial rotorcraft or helicopter (the drag `nav::drag` models).
        multirotor: bool,
    },
    /// An IMU sample.
    Imu(ImuReading),
    /// The autopilot's attitude estimate.
    Attitude(AttitudeReading),
    /// A GPS receiver's solution.
    Gps(GpsReading),
    /// The static pressure.
    Baro {
        /// `time_boot_ms` in µs.
        t_boot_us: u64,
        /// Absolute pressure, hPa.
        press_abs_hpa: f64,
    },
}

/// Which autopilot a HEARTBEAT names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Autopilot {
    /// PX4.
    Px4,
    /// ArduPilot.
    ArduPilot,
    /// Another autopilot.
    Other,
    /// MAV_AUTOPILOT_INVALID: not a flight controller (a GCS, a companion, a camera).
    Invalid,
}

/// Which message an IMU sample came from (in the order of preference: the finest first).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum ImuSource {
    /// HIGHRES_IMU (floats, SI).
    Highres = 0,
    /// SCALED_IMU (16-bit mG, mrad/s).
    Scaled = 1,
    /// RAW_IMU (ArduPilot: the same scaled 16-bit values).
    Raw = 2,
}

/// An IMU sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuReading {
    /// The message it came from.
    pub source: ImuSource,
    /// Autopilot boot time of the sample, µs.
    pub t_boot_us: u64,
    /// Body rates (FRD), rad/s.
    pub gyro_rad_s: [f64; 3],
    /// Specific force (FRD), m/s^2.
    pub accel_m_s2: [f64; 3],
    /// The 16-bit counts of a SCALED_IMU as sent (gyro mrad/s, accelerometer mG): PX4's bias
    /// restoration pairs them with HIGHRES_IMU at their own resolution.
    pub counts: Option<([i16; 3], [i16; 3])>,
}

/// The autopilot's attitude.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AttitudeReading {
    /// `time_boot_ms` in µs.
    pub t_boot_us: u64,
    /// Roll, pitch, yaw (ZYX), rad.
    pub roll_rad: f64,
    /// Pitch, rad.
    pub pitch_rad: f64,
    /// Yaw from north, rad.
    pub yaw_rad: f64,
    /// Body rates (roll, pitch, yaw speed), rad/s.
    pub rates_rad_s: [f64; 3],
}

/// A GPS receiver's solution.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GpsReading {
    /// 1: GPS_RAW_INT, 2: GPS2_RAW.
    pub receiver: u8,
    /// The message's `time_usec` (a boot time or, on ArduPilot, Unix time: the consumer decides).
    pub time_usec: u64,
    /// A 3-D fix or better.
    pub fix_3d: bool,
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above mean sea level, m.
    pub alt_amsl_m: f64,
    /// Ground speed, m/s (None: unknown).
    pub ground_speed_m_s: Option<f64>,
    /// Course over ground from north, degrees (None: unknown).
    pub course_deg: Option<f64>,
    /// Horizontal accuracy, m (None: not stated).
    pub h_acc_m: Option<f64>,
    /// Vertical accuracy, m (None: not stated).
    pub v_acc_m: Option<f64>,
    /// Speed accuracy, m/s (None: not stated).
    pub vel_acc_m_s: Option<f64>,
}

/// Whether a vehicle type flies on rotors whose drag `nav::drag` models.
pub fn is_multirotor(t: MavType) -> bool {
    matches!(
        t,
        MavType::MAV_TYPE_QUADROTOR
            | MavType::MAV_TYPE_HEXAROTOR
            | MavType::MAV_TYPE_OCTOROTOR
            | MavType::MAV_TYPE_TRICOPTER
            | MavType::MAV_TYPE_COAXIAL
            | MavType::MAV_TYPE_HELICOPTER
            | MavType::MAV_TYPE_DODECAROTOR
            | MavType::MAV_TYPE_DECAROTOR
    )
}

/// The 16-bit messages' units: mG and mrad/s.
fn mg(v: i16) -> f64 {
    f64::from(v) * 1e-3 * G0_M_S2
}
fn mrad(v: i16) -> f64 {
    f64::from(v) * 1e-3
}

/// A stated accuracy in mm (or mm/s): 0 means not stated.
fn stated_mm(v: u32) -> Option<f64> {
    (v > 0).then(|| f64::from(v) * 1e-3)
}

/// The reading of GPS_RAW_INT or GPS2_RAW (the fields they share).
fn gps(
    receiver: u8,
    time_usec: u64,
    fix: GpsFixType,
    [lat, lon, alt_mm]: [i32; 3],
    [vel, cog]: [u16; 2],
    [h_acc, v_acc, vel_acc]: [u32; 3],
) -> Sensor {
    Sensor::Gps(GpsReading {
        receiver,
        time_usec,
        fix_3d: (fix as u32) >= (GpsFixType::GPS_FIX_TYPE_3D_FIX as u32),
        lat_deg: f64::from(lat) * 1e-7,
        lon_deg: f64::from(lon) * 1e-7,
        alt_amsl_m: f64::from(alt_mm) * 1e-3,
        ground_speed_m_s: (vel != u16::MAX).then(|| f64::from(vel) * 0.01),
        course_deg: (cog != u16::MAX).then(|| f64::from(cog) * 0.01),
        h_acc_m: stated_mm(h_acc),
        v_acc_m: stated_mm(v_acc),
        vel_acc_m_s: stated_mm(vel_acc),
    })
}

impl Sensor {
    /// The reading a message carries; None for messages that are not sensor telemetry.
    pub fn from_message(msg: &MavMessage) -> Option<Self> {
        Some(match msg {
            MavMessage::HEARTBEAT(hb) => Self::Heartbeat {
                autopilot: match hb.autopilot {
                    MavAutopilot::MAV_AUTOPILOT_PX4 => Autopilot::Px4,
                    MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA => Autopilot::ArduPilot,
                    MavAutopilot::MAV_AUTOPILOT_INVALID => Autopilot::Invalid,
                    _ => Autopilot::Other,
                },
                multirotor: is_multirotor(hb.mavtype),
            },
            MavMessage::HIGHRES_IMU(m) => Self::Imu(ImuReading {
                source: ImuSource::Highres,
                t_boot_us: m.time_usec,
                gyro_rad_s: [m.xgyro, m.ygyro, m.zgyro].map(f64::from),
                accel_m_s2: [m.xacc, m.yacc, m.zacc].map(f64::from),
                counts: None,
            }),
            MavMessage::SCALED_IMU(m) => {
                let (g, a) = ([m.xgyro, m.ygyro, m.zgyro], [m.xacc, m.yacc, m.zacc]);
                Self::Imu(ImuReading {
                    source: ImuSource::Scaled,
                    t_boot_us: u64::from(m.time_boot_ms) * 1000,
                    gyro_rad_s: g.map(mrad),
                    accel_m_s2: a.map(mg),
                    counts: Some((g, a)),
                })
            }
            MavMessage::RAW_IMU(m) => Self::Imu(ImuReading {
                source: ImuSource::Raw,
                t_boot_us: m.time_usec,
                gyro_rad_s: [m.xgyro, m.ygyro, m.zgyro].map(mrad),
                accel_m_s2: [m.xacc, m.yacc, m.zacc].map(mg),
                counts: None,
            }),
            MavMessage::ATTITUDE(m) => Self::Attitude(AttitudeReading {
                t_boot_us: u64::from(m.time_boot_ms) * 1000,
                roll_rad: f64::from(m.roll),
                pitch_rad: f64::from(m.pitch),
                yaw_rad: f64::from(m.yaw),
                rates_rad_s: [m.rollspeed, m.pitchspeed, m.yawspeed].map(f64::from),
            }),
            MavMessage::GPS_RAW_INT(m) => gps(
                1,
                m.time_usec,
                m.fix_type,
                [m.lat, m.lon, m.alt],
                [m.vel, m.cog],
                [m.h_acc, m.v_acc, m.vel_acc],
            ),
            MavMessage::GPS2_RAW(m) => gps(
                2,
                m.time_usec,
                m.fix_type,
                [m.lat, m.lon, m.alt],
                [m.vel, m.cog],
                [m.h_acc, m.v_acc, m.vel_acc],
            ),
            MavMessage::SCALED_PRESSURE(m) => Self::Baro {
                t_boot_us: u64::from(m.time_boot_ms) * 1000,
                press_abs_hpa: f64::from(m.press_abs),
            },
            _ => return None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::ardupilotmega::{
        GPS_RAW_INT_DATA, HEARTBEAT_DATA, SCALED_IMU_DATA, SCALED_PRESSURE_DATA,
    };

    #[test]
    fn sixteen_bit_imu_counts_become_si_units_and_are_kept() {
        let m = MavMessage::SCALED_IMU(SCALED_IMU_DATA {
            time_boot_ms: 1500,
            xacc: 0,
            yacc: 0,
            zacc: -1000,
            xgyro: 10,
            ygyro: -20,
            zgyro: 0,
            ..Default::default()
        });
        let Some(Sensor::Imu(r)) = Sensor::from_message(&m) else {
            panic!("not an IMU reading");
        };
        assert_eq!(r.source, ImuSource::Scaled);
        assert_eq!(r.t_boot_us, 1_500_000);
        assert!((r.accel_m_s2[2] + G0_M_S2).abs() < 1e-12);
        assert!((r.gyro_rad_s[1] + 0.020).abs() < 1e-12);
        assert_eq!(r.counts, Some(([10, -20, 0], [0, 0, -1000])));
    }

    #[test]
    fn gps_unknowns_are_none_and_units_are_si() {
        let m = MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA {
            time_usec: 7,
            lat: 473_977_420,
            lon: 85_455_940,
            alt: 488_000,
            vel: u16::MAX,
            cog: 9000,
            fix_type: GpsFixType::GPS_FIX_TYPE_3D_FIX,
            h_acc: 0,
            v_acc: 1500,
            ..Default::default()
        });
        let Some(Sensor::Gps(g)) = Sensor::from_message(&m) else {
            panic!("not a GPS reading");
        };
        assert!(g.fix_3d && g.receiver == 1);
        assert!((g.lat_deg - 47.397742).abs() < 1e-9 && (g.alt_amsl_m - 488.0).abs() < 1e-9);
        assert_eq!((g.ground_speed_m_s, g.course_deg), (None, Some(90.0)));
        assert_eq!((g.h_acc_m, g.v_acc_m), (None, Some(1.5)));
        let two_d = MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA {
            fix_type: GpsFixType::GPS_FIX_TYPE_2D_FIX,
            ..Default::default()
        });
        assert!(matches!(Sensor::from_message(&two_d), Some(Sensor::Gps(g)) if !g.fix_3d));
    }

    #[test]
    fn heartbeats_name_the_autopilot_and_other_messages_are_not_sensors() {
        let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
            mavtype: MavType::MAV_TYPE_QUADROTOR,
            ..Default::default()
        });
        assert_eq!(
            Sensor::from_message(&hb),
            Some(Sensor::Heartbeat {
                autopilot: Autopilot::Px4,
                multirotor: true
            })
        );
        let p = MavMessage::SCALED_PRESSURE(SCALED_PRESSURE_DATA {
            time_boot_ms: 2,
            press_abs: 1013.25,
            ..Default::default()
        });
        assert_eq!(
            Sensor::from_message(&p),
            Some(Sensor::Baro {
                t_boot_us: 2000,
                press_abs_hpa: 1013.25
            })
        );
        let other = MavMessage::SYSTEM_TIME(Default::default());
        assert_eq!(Sensor::from_message(&other), None);
    }
}
