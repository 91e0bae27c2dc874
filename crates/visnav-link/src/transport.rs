//! The byte transports under the session: the mavlink crate's connections (TCP, serial, `udpout`,
//! `udpbcast`) and our own `udpin` listener (also `udp:`, which pymavlink opens as a listener).
//!
//! Why our own `udpin`: a UDP listener has no fixed peer, and the mavlink crate replies to the
//! source of the *last datagram received*, whatever it contained. One byte of junk from any local
//! process (with signing on or not) then steals the navigation stream from the autopilot.
//! [`UdpIn`] parses each datagram itself (CRC, and the signature when signing is
//! configured) and replies only to the address the *locked autopilot's* valid messages come from
//! ([`Transport::autopilot_heard`]). That address moves to a new one only after the current one
//! has been silent for the heartbeat timeout (an autopilot whose port changed after a restart),
//! and only on the locked autopilot's own valid messages; before the lock nothing is sent.

use std::collections::VecDeque;
use std::io::Cursor;
use std::net::SocketAddr;
use std::sync::Mutex;
use std::time::Duration;
use tokio::time::Instant;

use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::error::MessageReadError;
use mavlink::{AsyncMavConnection, MAVLinkMessageRaw, MavlinkReader, SigningConfig, SigningData};
use tokio::net::UdpSocket;

/// Largest UDP datagram.
const DATAGRAM_MAX: usize = 65_536;

/// One received frame and, for `udpin`, the address it came from.
pub(crate) struct Received {
    pub raw: MAVLinkMessageRaw,
    pub from: Option<SocketAddr>,
}

/// An open connection.
pub(crate) enum Transport {
    /// The mavlink crate's connection (TCP, serial, udpout, udpbcast).
    Mav(mavlink::AsyncConnection<MavMessage>),
    /// Our `udpin` listener.
    UdpIn(UdpIn),
}

/// A `udpin` listener that replies only to the locked autopilot (see the module doc).
pub(crate) struct UdpIn {
    socket: UdpSocket,
    signing: Option<SigningData>,
    queue: tokio::sync::Mutex<VecDeque<Received>>,
    /// The autopilot's address and when its last valid message came from there.
    peer: Mutex<Option<(SocketAddr, Instant)>>,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Transport {
    /// Open `address` (a connection string, `config::parse_connection`); `signing_in` verifies
    /// incoming frames.
    pub async fn connect(
        address: &str,
        signing_in: Option<&SigningConfig>,
    ) -> std::io::Result<Transport> {
        use mavlink::AsyncConnectable;
        // The configuration was checked at load; a string refused here is a caller's bug, and
        // an error (not a panic) keeps the link retrying and saying why.
        let endpoint = crate::config::parse_connection(address)
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e.to_string()))?;
        if let crate::config::Endpoint::UdpIn(bind) = &endpoint {
            let socket = UdpSocket::bind(bind.as_str()).await?;
            return Ok(Transport::UdpIn(UdpIn {
                socket,
                signing: signing_in.cloned().map(SigningData::from_config),
                queue: tokio::sync::Mutex::new(VecDeque::new()),
                peer: Mutex::new(None),
            }));
        }
        let mut conn = match (&endpoint, endpoint.mavlink_address()) {
            // Built directly: a device path may hold colons the crate's parser would split at.
            (crate::config::Endpoint::Serial { device, baud }, _) => {
                mavlink::ConnectionAddress::Serial(mavlink::SerialConfig::new(
                    device.clone(),
                    *baud,
                ))
                .connect_async::<MavMessage>()
                .await?
            }
            (_, Some(a)) => mavlink::connect_async::<MavMessage>(&a).await?,
            (_, None) => {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    "no transport for this connection",
                ));
            }
        };
        conn.set_allow_recv_any_version(true);
        if let Some(s) = signing_in {
            conn.setup_signing(Some(s.clone()));
        }
        Ok(Transport::Mav(conn))
    }

    /// The next valid frame.
    pub async fn recv(&self) -> Result<Received, MessageReadError> {
        match self {
            Transport::Mav(c) => c.recv_raw().await.map(|raw| Received { raw, from: None }),
            Transport::UdpIn(u) => u.recv().await,
        }
    }

    /// Send one frame; `Ok(0)` when there is nobody to send to yet (`udpin` before the lock).
    pub async fn send_raw(&self, raw: &MAVLinkMessageRaw) -> std::io::Result<usize> {
        match self {
            Transport::Mav(c) => c
                .send_raw(raw)
                .await
                .map_err(|e| std::io::Error::other(e.to_string())),
            Transport::UdpIn(u) => {
                let Some((peer, _)) = *lock(&u.peer) else {
                    return Ok(0);
                };
                let bytes = match raw {
                    MAVLinkMessageRaw::V1(m) => m.raw_bytes(),
                    MAVLinkMessageRaw::V2(m) => m.raw_bytes(),
                };
                u.socket.send_to(bytes, peer).await
            }
        }
    }

    /// A valid message of the locked autopilot came from `from`: make it the reply address when
    /// there is none, or when the current one has been silent for `silence`.
    pub fn autopilot_heard(
        &self,
        from: Option<SocketAddr>,
        silence: Duration,
    ) -> Option<SocketAddr> {
        let (Transport::UdpIn(u), Some(from)) = (self, from) else {
            return None;
        };
        let mut peer = lock(&u.peer);
        let now = Instant::now();
        match *peer {
            Some((addr, _)) if addr == from => {
                *peer = Some((addr, now));
                None
            }
            Some((_, last)) if now.duration_since(last) < silence => None,
            _ => {
                *peer = Some((from, now));
                Some(from)
            }
        }
    }
}

impl UdpIn {
    async fn recv(&self) -> Result<Received, MessageReadError> {
        let mut queue = self.queue.lock().await;
        let mut buf = vec![0u8; DATAGRAM_MAX];
        loop {
            if let Some(r) = queue.pop_front() {
                return Ok(r);
            }
            let (n, from) = self.socket.recv_from(&mut buf).await?;
            let mut reader = MavlinkReader::new(Cursor::new(&buf[..n]));
            // Every valid (and, with signing, authenticated) frame of the datagram; the reader
            // skips bytes that do not make a frame and ends with an error at the datagram's end.
            while let Ok(raw) =
                reader.read_any_raw_message_signed::<MavMessage>(self.signing.as_ref())
            {
                queue.push_back(Received {
                    raw,
                    from: Some(from),
                });
            }
        }
    }
}
