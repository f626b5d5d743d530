//! `mac-bridge certs`: the swarm's own certificate authority and one certificate per host, for
//! the bridges' mutually authenticated TLS links (see `network`).
//!
//! Files written into the output folder (PEM):
//! - `ca.pem`: the swarm CA's certificate. Every host gets a copy: it is what a bridge trusts.
//! - `ca.key`: the CA's private key. Only needed to issue more certificates; keep it off the
//!   hosts.
//! - `HOST.pem`, `HOST.key`: each host's certificate and private key (the same pair serves the
//!   listening and the connecting side). Copy them to that host only.
//!
//! A host certificate names the host (common name) and the addresses other hosts use to reach
//! it (subject alternative names, IP addresses or DNS names): a connecting bridge checks that
//! the host it reached is the one its endpoint names. Hosts that only connect need no address.
//! Keys are ECDSA P-256; private key files are readable by their owner only.

use std::fs::OpenOptions;
use std::io::Write;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use anyhow::{Context, Result, bail};
use rcgen::{
    BasicConstraints, CertificateParams, CertifiedIssuer, DnType, ExtendedKeyUsagePurpose, IsCa,
    KeyPair, KeyUsagePurpose,
};
use time::{Duration, OffsetDateTime};

/// File name of the swarm CA's certificate in a certificates folder.
pub const CA_CERTIFICATE: &str = "ca.pem";
const CA_PRIVATE_KEY: &str = "ca.key";
/// Validity starts this long before the certificates are made, so a host whose clock is a
/// little behind still accepts them.
const CLOCK_SKEW: Duration = Duration::hours(1);

/// A host to certify: `NAME` or `NAME=ADDRESS,ADDRESS...`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HostSpec {
    pub name: String,
    /// IP addresses or DNS names other hosts connect to this host by.
    pub addresses: Vec<String>,
}

impl FromStr for HostSpec {
    type Err = anyhow::Error;

    fn from_str(spec: &str) -> Result<Self> {
        let (name, addresses) = match spec.split_once('=') {
            Some((name, list)) => (name, list.split(',').map(str::to_string).collect()),
            None => (spec, Vec::new()),
        };
        check_host_name(name)?;
        if addresses.iter().any(String::is_empty) {
            bail!("host '{spec}': an empty address in the list");
        }
        Ok(Self {
            name: name.to_string(),
            addresses,
        })
    }
}

/// A host name is a file name in the certificates folder.
fn check_host_name(name: &str) -> Result<()> {
    let allowed = |c: char| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.');
    if name.is_empty() || name.starts_with('.') || !name.chars().all(allowed) {
        bail!("host name '{name}': use letters, digits, '-', '_' and '.' (it names its files)");
    }
    if name == "ca" {
        bail!("host name 'ca' is taken by the certificate authority's files");
    }
    Ok(())
}

/// Paths of one host's files in a certificates folder.
#[derive(Debug, Clone)]
pub struct HostFiles {
    pub ca_certificate: PathBuf,
    pub certificate: PathBuf,
    pub private_key: PathBuf,
}

impl HostFiles {
    pub fn in_folder(folder: &Path, host: &str) -> Self {
        Self {
            ca_certificate: folder.join(CA_CERTIFICATE),
            certificate: folder.join(format!("{host}.pem")),
            private_key: folder.join(format!("{host}.key")),
        }
    }
}

/// Makes a new swarm CA and a certificate for each host into `folder` (created if missing),
/// valid for `days`. Refuses to overwrite existing files: a second CA would not be trusted by
/// the hosts holding the first one's certificates.
pub fn make(folder: &Path, hosts: &[HostSpec], days: u32) -> Result<()> {
    if hosts.is_empty() {
        bail!("give at least one --host NAME[=ADDRESS,...]");
    }
    for (i, host) in hosts.iter().enumerate() {
        if hosts[..i].iter().any(|other| other.name == host.name) {
            bail!("host '{}' is given twice", host.name);
        }
    }
    std::fs::create_dir_all(folder)
        .with_context(|| format!("creating the certificates folder {}", folder.display()))?;
    let not_before = OffsetDateTime::now_utc() - CLOCK_SKEW;
    let not_after = not_before + CLOCK_SKEW + Duration::days(i64::from(days));

    let mut ca_params = CertificateParams::default();
    ca_params.distinguished_name = rcgen::DistinguishedName::new();
    ca_params
        .distinguished_name
        .push(DnType::CommonName, "mac-ego3d swarm CA");
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    ca_params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    (ca_params.not_before, ca_params.not_after) = (not_before, not_after);
    let ca = CertifiedIssuer::self_signed(ca_params, KeyPair::generate()?)
        .context("making the swarm CA certificate")?;
    write_new(&folder.join(CA_CERTIFICATE), &ca.pem(), false)?;
    write_new(
        &folder.join(CA_PRIVATE_KEY),
        &ca.key().serialize_pem(),
        true,
    )?;

    for host in hosts {
        let mut params = CertificateParams::new(host.addresses.clone())
            .with_context(|| format!("host '{}': addresses {:?}", host.name, host.addresses))?;
        params.distinguished_name = rcgen::DistinguishedName::new();
        params
            .distinguished_name
            .push(DnType::CommonName, host.name.as_str());
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        // One pair for both sides of a link: a host both listens and connects.
        params.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        params.use_authority_key_identifier_extension = true;
        (params.not_before, params.not_after) = (not_before, not_after);
        let key = KeyPair::generate()?;
        let certificate = params
            .signed_by(&key, &ca)
            .with_context(|| format!("signing the certificate of host '{}'", host.name))?;
        let files = HostFiles::in_folder(folder, &host.name);
        write_new(&files.certificate, &certificate.pem(), false)?;
        write_new(&files.private_key, &key.serialize_pem(), true)?;
        tracing::info!(host = %host.name, addresses = ?host.addresses,
            certificate = %files.certificate.display(), "host certificate made");
    }
    tracing::info!(folder = %folder.display(), days,
        "swarm CA made: copy {CA_CERTIFICATE} and each host's NAME.pem and NAME.key to that host; keep {CA_PRIVATE_KEY} off the hosts");
    Ok(())
}

/// Writes a file that must not exist yet; a private one is readable by its owner only.
fn write_new(path: &Path, text: &str, private: bool) -> Result<()> {
    let mut file = OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(if private { 0o600 } else { 0o644 })
        .open(path)
        .with_context(|| format!("writing {} (it must not exist yet)", path.display()))?;
    file.write_all(text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn host_specs_parse_and_bad_names_are_refused() {
        let host: HostSpec = "consensus=192.168.1.10,slam-server".parse().unwrap();
        assert_eq!(host.name, "consensus");
        assert_eq!(host.addresses, ["192.168.1.10", "slam-server"]);
        assert!("agent0".parse::<HostSpec>().unwrap().addresses.is_empty());
        for bad in ["", "ca", "../x", "a/b", ".hidden", "x=1.2.3.4,"] {
            assert!(bad.parse::<HostSpec>().is_err(), "{bad:?} was accepted");
        }
    }

    #[test]
    fn makes_ca_and_host_files_and_never_overwrites() {
        let folder = std::env::temp_dir().join(format!("mac-certs-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&folder);
        let hosts = ["consensus=127.0.0.1", "agent0"].map(|h| h.parse().unwrap());
        make(&folder, &hosts, 30).unwrap();
        for name in [
            "ca.pem",
            "ca.key",
            "consensus.pem",
            "consensus.key",
            "agent0.pem",
        ] {
            let text = std::fs::read_to_string(folder.join(name)).unwrap();
            assert!(text.starts_with("-----BEGIN "), "{name}");
        }
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(folder.join("agent0.key"))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o077, 0, "a private key is readable by others");
        let again = make(&folder, &hosts, 30).unwrap_err();
        assert!(
            format!("{again:#}").contains("must not exist yet"),
            "{again:#}"
        );
        std::fs::remove_dir_all(&folder).unwrap();
    }
}
