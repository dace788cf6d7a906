//! How full a fleet node is: the sessions on its listening ports, counted from the kernel's
//! socket table (`/proc/net/tcp`, `/proc/net/tcp6`: one established connection a session, TLS
//! or not), against the sessions it accepts. zenoh's own session list is behind its unstable
//! admin space; the kernel's table is there on every Linux router. Pure: the table's text in,
//! counts out.

/// The port of a zenoh endpoint (`tls/0.0.0.0:7447`, `tcp/[::]:7447#iface=eth0`).
pub fn port_of(endpoint: &str) -> Option<u16> {
    let address = endpoint.split(['#', '?']).next()?;
    address.rsplit(':').next()?.parse().ok()
}

/// Connections established on one of `ports` (the local side), in a `/proc/net/tcp` or
/// `/proc/net/tcp6` table's text. Lines that do not parse are skipped.
pub fn established_on(table: &str, ports: &[u16]) -> usize {
    table
        .lines()
        .skip(1)
        .filter(|line| {
            let mut fields = line.split_whitespace();
            let local = fields.nth(1);
            let state = fields.nth(1);
            let port = local
                .and_then(|l| l.rsplit(':').next())
                .and_then(|p| u16::from_str_radix(p, 16).ok());
            // State 01: TCP_ESTABLISHED.
            state == Some("01") && port.is_some_and(|p| ports.contains(&p))
        })
        .count()
}

/// How full a node is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fullness {
    /// Below 90 % of what it accepts.
    Room,
    /// At 90 % or more: the next robots may soon be refused.
    Near,
    /// At what it accepts: a new robot is refused.
    Full,
}

/// `sessions` against `max_sessions`.
pub fn fullness(sessions: usize, max_sessions: usize) -> Fullness {
    if sessions >= max_sessions {
        Fullness::Full
    } else if sessions * 10 >= max_sessions * 9 {
        Fullness::Near
    } else {
        Fullness::Room
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // Lines as the kernel writes them: a listener on 7447 (0A), two sessions on it, one in
    // TIME_WAIT (06), and the router's own link out from an ephemeral port.
    const TABLE: &str = "  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode
   0: 00000000:1D17 00000000:0000 0A 00000000:00000000 00:00000000 00000000     0        0 1 1 0000000000000000 100 0 0 10 0
   1: 0100007F:1D17 0100007F:C4A2 01 00000000:00000000 00:00000000 00000000     0        0 2 1 0000000000000000 20 4 30 10 -1
   2: 0100007F:1D17 0100007F:C4A4 01 00000000:00000000 00:00000000 00000000     0        0 3 1 0000000000000000 20 4 30 10 -1
   3: 0100007F:1D17 0100007F:C4A6 06 00000000:00000000 00:00000000 00000000     0        0 0 1 0000000000000000 20 4 30 10 -1
   4: 0100007F:C4A8 0100007F:1D17 01 00000000:00000000 00:00000000 00000000     0        0 4 1 0000000000000000 20 4 30 10 -1
";

    #[test]
    fn only_sessions_established_on_the_listening_port_count() {
        assert_eq!(established_on(TABLE, &[7447]), 2);
        assert_eq!(established_on(TABLE, &[7448]), 0);
        assert_eq!(established_on("garbage\nmore garbage here 01", &[7447]), 0);
        let v6 =
            "  sl  local_address                         remote_address                        st
   0: 00000000000000000000000001000000:1D17 00000000000000000000000001000000:D2F0 01 0";
        assert_eq!(established_on(v6, &[7447]), 1);
    }

    #[test]
    fn an_endpoint_s_port_is_read_with_or_without_its_options() {
        assert_eq!(port_of("tls/0.0.0.0:7447"), Some(7447));
        assert_eq!(port_of("tcp/[::]:7448#iface=eth0"), Some(7448));
        assert_eq!(port_of("tls/fleet.example.org:7447"), Some(7447));
        assert_eq!(port_of("unixsock-stream/tmp/z"), None);
    }

    #[test]
    fn a_node_is_near_full_at_ninety_percent_and_full_at_its_limit() {
        assert_eq!(fullness(899, 1000), Fullness::Room);
        assert_eq!(fullness(900, 1000), Fullness::Near);
        assert_eq!(fullness(999, 1000), Fullness::Near);
        assert_eq!(fullness(1000, 1000), Fullness::Full);
    }
}
