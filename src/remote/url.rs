//! The `server` URL: parsing, the credentials it may carry, how it is shown, and which server
//! it names (the key of the process-wide in-flight bound).
//!
//! `http://[user[:password]@]host[:port][/prefix]` or `https://...`; the scheme and the host are
//! case-insensitive, the port defaults to 80 / 443, trailing slashes do not matter. Userinfo is
//! sent as HTTP basic authentication (percent-decoded, as curl does) and is never shown:
//! [`display_url`] replaces it with `***` wherever a server URL reaches a message, a log or
//! `leangate-stats`.

use std::fmt;
use std::net::{IpAddr, Ipv6Addr};

use base64::Engine as _;

/// How a server URL is shown in messages, logs and stats: as written, with any userinfo (user
/// name, password, token) replaced by `***` and trailing slashes dropped. Works on any text,
/// parseable or not, so that a URL refused at start is shown without its credentials too.
pub fn display_url(raw: &str) -> String {
    let raw = raw.trim();
    let (scheme, rest) = match raw.split_once("://") {
        Some((s, r)) => (&raw[..s.len() + 3], r),
        None => ("", raw),
    };
    // The last `@` ends the userinfo; a password holding an unencoded `/`, `?` or `#` still
    // ends before it, so everything before it goes.
    let rest = match rest.rfind('@') {
        Some(i) => format!("***@{}", &rest[i + 1..]),
        None => rest.to_string(),
    };
    format!("{scheme}{}", rest.trim_end_matches('/'))
}

/// A parsed `server` URL.
#[derive(Clone, PartialEq, Eq)]
pub struct ServerUrl {
    https: bool,
    userinfo: Option<String>,
    /// Lowercased; an IPv6 address keeps its brackets.
    host: String,
    port: Option<u16>,
    /// `""` or `/prefix` without a trailing slash.
    path: String,
    shown: String,
}

impl fmt::Display for ServerUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.shown)
    }
}

impl fmt::Debug for ServerUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ServerUrl({})", self.shown)
    }
}

impl ServerUrl {
    /// Whether the URL is `https://`.
    pub fn is_https(&self) -> bool {
        self.https
    }

    /// Parse `raw`; the error says what is wrong (the caller names the URL, shown with
    /// [`display_url`]).
    pub fn parse(raw: &str) -> Result<ServerUrl, String> {
        let raw = raw.trim();
        let Some((scheme, rest)) = raw.split_once("://") else {
            return Err("expected http://host:port or https://host:port".into());
        };
        let https = match scheme.to_ascii_lowercase().as_str() {
            "http" => false,
            "https" => true,
            "grpc" | "grpcs" => {
                return Err("gRPC is not supported yet; use the server's HTTP endpoint \
                            (Triton: http://host:8000)"
                    .into())
            }
            _ => return Err("expected http://host:port or https://host:port".into()),
        };
        if rest.contains(['?', '#']) {
            return Err("a server URL has no query or fragment".into());
        }
        let (authority, path) = rest.split_at(rest.find('/').unwrap_or(rest.len()));
        // An `@` after the host is a password holding an unencoded `/` (`user:pa/ss@host`): read
        // as written, the host would be the user name and the secret would go to DNS and to
        // whatever answers there, while every message shows the real host.
        if path.contains('@') {
            return Err(
                "`@` after the host: a user name or password holding `/` must be \
                        percent-encoded (`/` as %2F)"
                    .into(),
            );
        }
        let (userinfo, hostport) = match authority.rsplit_once('@') {
            Some((u, h)) => (Some(u.to_string()), h),
            None => (None, authority),
        };
        if hostport.is_empty() {
            return Err("no host".into());
        }
        let (host, port) = if let Some(v6) = hostport.strip_prefix('[') {
            let (addr, after) = v6
                .split_once(']')
                .ok_or("an IPv6 address needs its closing `]`")?;
            addr.parse::<Ipv6Addr>()
                .map_err(|_| format!("`[{addr}]` is not an IPv6 address"))?;
            let port = match after {
                "" => None,
                p => Some(p.strip_prefix(':').ok_or_else(|| {
                    format!("`{after}` after the IPv6 address; expected `:port`")
                })?),
            };
            (format!("[{}]", addr.to_ascii_lowercase()), port)
        } else {
            let (host, port) = match hostport.split_once(':') {
                Some((h, p)) => (h, Some(p)),
                None => (hostport, None),
            };
            if port.is_some_and(|p| p.contains(':')) {
                return Err("an IPv6 address goes in brackets (http://[::1]:8000)".to_string());
            }
            if host.is_empty() {
                return Err("no host".into());
            }
            if !host
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '.' | '_'))
            {
                return Err(format!("`{host}` is not a host name or address"));
            }
            (host.to_ascii_lowercase(), port)
        };
        let port = port.map(parse_port).transpose()?;
        Ok(ServerUrl {
            https,
            userinfo,
            host,
            port,
            path: path.trim_end_matches('/').to_string(),
            shown: display_url(raw),
        })
    }

    /// The URL requests go to: scheme, host, port as given, prefix; never the userinfo.
    pub fn base(&self) -> String {
        let port = self.port.map(|p| format!(":{p}")).unwrap_or_default();
        format!(
            "{}://{}{port}{}",
            if self.https { "https" } else { "http" },
            self.host,
            self.path
        )
    }

    /// The `Authorization` header value for the userinfo (HTTP basic), if any.
    pub fn authorization(&self) -> Option<String> {
        let userinfo = self.userinfo.as_deref()?;
        let (user, password) = userinfo.split_once(':').unwrap_or((userinfo, ""));
        let pair = [
            percent_decode(user),
            b":".to_vec(),
            percent_decode(password),
        ]
        .concat();
        Some(format!(
            "Basic {}",
            base64::engine::general_purpose::STANDARD.encode(pair)
        ))
    }

    /// Which server this is, for the process-wide in-flight bound: the scheme, the host
    /// (lowercased; every loopback spelling, `localhost`, `127.x.x.x` and `[::1]`, is one
    /// host), the port (the scheme's default when not given) and the prefix. Credentials do
    /// not count.
    pub fn server_key(&self) -> String {
        let bare = self.host.trim_start_matches('[').trim_end_matches(']');
        let host = match bare.parse::<IpAddr>() {
            Ok(ip) if is_loopback(ip) => "localhost".to_string(),
            Ok(IpAddr::V6(ip)) => format!("[{ip}]"),
            Ok(ip) => ip.to_string(),
            Err(_) if bare.trim_end_matches('.') == "localhost" => "localhost".to_string(),
            Err(_) => bare.trim_end_matches('.').to_string(),
        };
        let port = self.port.unwrap_or(if self.https { 443 } else { 80 });
        format!(
            "{}://{host}:{port}{}",
            if self.https { "https" } else { "http" },
            self.path
        )
    }
}

fn is_loopback(ip: IpAddr) -> bool {
    match ip {
        IpAddr::V4(v4) => v4.is_loopback(),
        IpAddr::V6(v6) => {
            v6.is_loopback() || v6.to_ipv4_mapped().is_some_and(|v4| v4.is_loopback())
        }
    }
}

fn parse_port(p: &str) -> Result<u16, String> {
    if p.is_empty() {
        return Err("no port after `:`".into());
    }
    if !p.bytes().all(|b| b.is_ascii_digit()) {
        return Err(format!("port `{p}` is not a number"));
    }
    match p.parse::<u32>() {
        Ok(n @ 1..=65535) => Ok(n as u16),
        _ => Err(format!("port {p} is not a valid TCP port (1 to 65535)")),
    }
}

/// `%XX` sequences to bytes; anything else as it is.
fn percent_decode(s: &str) -> Vec<u8> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        let hex = |c: u8| (c as char).to_digit(16);
        match (
            b[i],
            b.get(i + 1).and_then(|&c| hex(c)),
            b.get(i + 2).and_then(|&c| hex(c)),
        ) {
            (b'%', Some(h), Some(l)) => {
                out.push((h * 16 + l) as u8);
                i += 3;
            }
            (c, _, _) => {
                out.push(c);
                i += 1;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn display_hides_userinfo_everywhere() {
        assert_eq!(display_url("http://u:secret@h:8000/"), "http://***@h:8000");
        assert_eq!(display_url("https://token@h"), "https://***@h");
        assert_eq!(display_url("ftp://u:pw@x"), "ftp://***@x");
        assert_eq!(display_url("u:pw@h:1"), "***@h:1");
        // An unencoded `/` or `@` in the password still goes.
        assert_eq!(display_url("http://u:se/cr@t@h:1"), "http://***@h:1");
        assert_eq!(display_url("http://"), "http://");
        assert_eq!(display_url("HTTP://Host:8/p//"), "HTTP://Host:8/p");
    }

    #[test]
    fn parses_and_refuses_clearly() {
        let u = ServerUrl::parse(" HTTP://User:p%40ss@LocalHost:8000/triton/ ").unwrap();
        assert_eq!(u.base(), "http://localhost:8000/triton");
        assert_eq!(u.to_string(), "HTTP://***@LocalHost:8000/triton");
        // "User:p@ss"
        assert_eq!(u.authorization().unwrap(), "Basic VXNlcjpwQHNz");
        assert_eq!(ServerUrl::parse("https://h").unwrap().authorization(), None);
        let err = |s: &str| ServerUrl::parse(s).unwrap_err();
        assert!(err("http://").contains("no host"));
        assert!(err("http://h:99999").contains("port 99999 is not a valid TCP port"));
        assert!(err("http://h:0").contains("port 0"));
        assert!(err("http://h:8o").contains("not a number"));
        assert!(err("http://h:").contains("no port"));
        assert!(err("grpc://h:8001").contains("gRPC"));
        assert!(err("h:8000").contains("http://"));
        assert!(err("http://::1:8000").contains("brackets"));
        assert!(err("http://h:1/?x").contains("query"));
        assert!(err("http://h st:1").contains("host name"));
        let v6 = ServerUrl::parse("http://[::1]:8000").unwrap();
        assert_eq!(v6.base(), "http://[::1]:8000");
    }

    #[test]
    fn one_key_per_server() {
        let key = |s: &str| ServerUrl::parse(s).unwrap().server_key();
        let k = key("http://127.0.0.1:8000");
        for same in [
            "http://127.0.0.1:8000/",
            "HTTP://localhost:8000",
            "http://LOCALHOST.:8000//",
            "http://[::1]:8000",
            "http://[0:0:0:0:0:0:0:1]:8000",
            "http://u:p@127.0.0.1:8000",
        ] {
            assert_eq!(key(same), k, "{same}");
        }
        assert_eq!(key("http://gpu:80"), key("http://GPU"));
        assert_eq!(key("https://gpu:443/"), key("https://gpu"));
        for other in [
            "https://127.0.0.1:8000",
            "http://127.0.0.1:8001",
            "http://127.0.0.1:8000/other",
            "http://gpu:8000",
        ] {
            assert_ne!(key(other), k, "{other}");
        }
    }
}
