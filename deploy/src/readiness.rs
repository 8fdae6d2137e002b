//! Readiness: the supervisor pings its own front-end over XRCE (GET_INFO, the same ping a
//! client uses) and, once answered, reports the agent ready, to systemd too when run under it
//! (`Type=notify`).

use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use xrce_common::session::client::{Client, ClientConfig, ClientEvent};
use xrce_common::wire::ClientKey;

/// Pings `agent` until it answers INFO or `timeout` passes; returns whether it answered.
pub fn wait_until_serving(agent: SocketAddr, timeout: Duration) -> bool {
    let local: SocketAddr = if agent.is_ipv4() {
        ([127, 0, 0, 1], 0).into()
    } else {
        (std::net::Ipv6Addr::LOCALHOST, 0).into()
    };
    let Ok(socket) = UdpSocket::bind(local) else {
        return false;
    };
    if socket.connect(agent).is_err()
        || socket
            .set_read_timeout(Some(Duration::from_millis(100)))
            .is_err()
    {
        return false;
    }
    let mut client = Client::new(ClientConfig::new(ClientKey(*b"RDY?")));
    let mut buf = [0u8; 512];
    let end = Instant::now() + timeout;
    while Instant::now() < end {
        client.ping();
        while let Some(t) = client.poll_transmit() {
            let _ = socket.send(&t);
        }
        if let Ok(n) = socket.recv(&mut buf) {
            client.handle_datagram(Instant::now(), &buf[..n]);
            if std::iter::from_fn(|| client.poll_event()).any(|e| matches!(e, ClientEvent::Info(_)))
            {
                return true;
            }
        } else {
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    false
}

/// The address to ping for a front-end bound to `bind` (wildcards become loopback).
pub fn probe_address(bind: SocketAddr) -> SocketAddr {
    match bind {
        SocketAddr::V4(a) if a.ip().is_unspecified() => ([127, 0, 0, 1], a.port()).into(),
        SocketAddr::V6(a) if a.ip().is_unspecified() => {
            (std::net::Ipv6Addr::LOCALHOST, a.port()).into()
        }
        other => other,
    }
}

/// Sends `state` (e.g. `READY=1`) to systemd if `NOTIFY_SOCKET` is set; returns whether sent.
pub fn notify_systemd(state: &str) -> std::io::Result<bool> {
    use std::os::unix::net::{SocketAddr as UnixAddr, UnixDatagram};
    let Some(path) = std::env::var_os("NOTIFY_SOCKET") else {
        return Ok(false);
    };
    let socket = UnixDatagram::unbound()?;
    let bytes = path.as_encoded_bytes();
    let addr = if let Some(abstract_name) = bytes.strip_prefix(b"@") {
        use std::os::linux::net::SocketAddrExt;
        UnixAddr::from_abstract_name(abstract_name)?
    } else {
        UnixAddr::from_pathname(std::path::Path::new(&path))?
    };
    socket.send_to_addr(state.as_bytes(), &addr)?;
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn notifies_a_unix_socket() {
        let dir = std::env::temp_dir().join(format!("xrce-notify-{}", std::process::id()));
        let _ = std::fs::create_dir_all(&dir);
        let path = dir.join("notify.sock");
        let _ = std::fs::remove_file(&path);
        let listener = std::os::unix::net::UnixDatagram::bind(&path).expect("bind");
        // Set for this test process only; no other test in this crate reads NOTIFY_SOCKET.
        std::env::set_var("NOTIFY_SOCKET", &path);
        assert!(notify_systemd("READY=1").expect("send"));
        let mut buf = [0u8; 32];
        let n = listener.recv(&mut buf).expect("recv");
        assert_eq!(&buf[..n], b"READY=1");
        std::env::remove_var("NOTIFY_SOCKET");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn nobody_listening_is_not_ready() {
        let port = UdpSocket::bind("127.0.0.1:0")
            .and_then(|s| s.local_addr())
            .expect("port");
        assert!(!wait_until_serving(port, Duration::from_millis(300)));
        assert_eq!(
            probe_address("0.0.0.0:8888".parse().expect("addr")),
            "127.0.0.1:8888".parse().expect("addr")
        );
    }
}
