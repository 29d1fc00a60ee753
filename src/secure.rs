//! `glasshouse secure`: a certificate authority, a key and certificate per identity, the router's
//! mTLS + ACL config and one client config per identity. What each identity may do comes from
//! `glasshouse_trust`; this module makes the keys and writes the files.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use glasshouse_trust::{
    client_config, config_text, router_config, Identity, Kind, Layout, Roster, ROUTER,
};
use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa,
    Issuer, KeyPair, KeyUsagePurpose,
};

#[derive(clap::Args, Debug)]
pub struct SecureArgs {
    #[command(subcommand)]
    command: SecureCommand,
}

#[derive(clap::Subcommand, Debug)]
enum SecureCommand {
    /// Create a deployment's PKI in DIR: CA, router and identity keys and certificates, the
    /// router's config (mTLS listener + ACL) and one client config per identity.
    Init(InitArgs),
    /// Add one identity to an existing PKI, signed by its CA, and regenerate router.json5's ACL
    /// (restart the router to apply it).
    Issue(IssueArgs),
    /// Try, from outside, what the deployment must refuse: connecting without a certificate or
    /// with another CA's, and a trolley identity writing another trolley's keys, views and ROI
    /// clouds, posing as a planner or detector, or asking for map snapshots. Prints each attempt;
    /// exits non-zero when any got through.
    Probe(crate::probe::ProbeArgs),
}

#[derive(clap::Args, Debug)]
struct InitArgs {
    /// Directory to write to (created; must not hold a CA yet).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Roster file (JSON5: { trolleys: [..], planners: [..], detectors: [..], dashboards: [..],
    /// router_hosts: [..], router_endpoint: ".." }); the flags below add to it.
    #[arg(long, value_name = "FILE")]
    roster: Option<PathBuf>,
    /// Trolley ids, comma-separated; each gets the identity trolley-<id>.
    #[arg(long, value_name = "IDS", value_delimiter = ',')]
    trolleys: Vec<String>,
    /// Planner ids, comma-separated; each gets the identity planner-<id>.
    #[arg(long, value_name = "IDS", value_delimiter = ',')]
    planners: Vec<String>,
    /// Detector ids, comma-separated; each gets the identity detector-<id>.
    #[arg(long, value_name = "IDS", value_delimiter = ',')]
    detectors: Vec<String>,
    /// Dashboard ids, comma-separated; each gets the identity dashboard-<id> (read-only).
    #[arg(long, value_name = "IDS", value_delimiter = ',')]
    dashboards: Vec<String>,
    /// Names the router's certificate is valid for, comma-separated (DNS names or IPs)
    /// [default: localhost,127.0.0.1,router, or the roster's].
    #[arg(long, value_name = "HOSTS", value_delimiter = ',')]
    router_hosts: Vec<String>,
    /// Where clients connect, tls/HOST:PORT with HOST among the router hosts; the router listens
    /// on tls/0.0.0.0:PORT [default: tls/127.0.0.1:7447, or the roster's].
    #[arg(long, value_name = "ENDPOINT")]
    router_endpoint: Option<String>,
    /// Absolute directory where the processes will read these files, when not --out (e.g. a
    /// volume mounted at /etc/glasshouse/pki): the configs name the files there.
    #[arg(long, value_name = "DIR")]
    install_dir: Option<String>,
    #[command(flatten)]
    validity: Validity,
}

#[derive(clap::Args, Debug)]
#[group(required = true, multiple = false)]
struct NewIdentity {
    /// Add trolley <ID> (identity trolley-<ID>).
    #[arg(long, value_name = "ID")]
    trolley: Option<String>,
    /// Add planner <ID>.
    #[arg(long, value_name = "ID")]
    planner: Option<String>,
    /// Add detector <ID>.
    #[arg(long, value_name = "ID")]
    detector: Option<String>,
    /// Add dashboard <ID>.
    #[arg(long, value_name = "ID")]
    dashboard: Option<String>,
}

impl NewIdentity {
    fn identity(&self) -> anyhow::Result<Identity> {
        let given = [
            (Kind::Trolley, &self.trolley),
            (Kind::Planner, &self.planner),
            (Kind::Detector, &self.detector),
            (Kind::Dashboard, &self.dashboard),
        ];
        let (kind, id) = given
            .into_iter()
            .find_map(|(kind, id)| id.as_ref().map(|id| (kind, id)))
            .context("name one identity")?;
        Ok(Identity::new(kind, id)?)
    }
}

#[derive(clap::Args, Debug)]
struct IssueArgs {
    /// Directory of an existing PKI (made by `secure init`).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    #[command(flatten)]
    identity: NewIdentity,
    #[command(flatten)]
    validity: Validity,
}

#[derive(clap::Args, Debug, Clone, Copy)]
struct Validity {
    /// How long the new certificates are valid, in days from now.
    #[arg(long, value_name = "DAYS", default_value_t = 825)]
    valid_days: u32,
}

pub async fn run(args: SecureArgs) -> anyhow::Result<()> {
    match args.command {
        SecureCommand::Init(args) => init(args),
        SecureCommand::Issue(args) => issue(args),
        SecureCommand::Probe(args) => crate::probe::run(args).await,
    }
}

fn roster_from(args: &InitArgs) -> anyhow::Result<Roster> {
    let mut roster = match &args.roster {
        Some(path) => Roster::parse(&read(path)?).with_context(|| path.display().to_string())?,
        None => Roster::default(),
    };
    let given = [
        (Kind::Trolley, &args.trolleys),
        (Kind::Planner, &args.planners),
        (Kind::Detector, &args.detectors),
        (Kind::Dashboard, &args.dashboards),
    ];
    for (kind, ids) in given {
        for id in ids {
            roster.add(&Identity::new(kind, id)?)?;
        }
    }
    if !args.router_hosts.is_empty() {
        roster.router_hosts = args.router_hosts.clone();
    }
    if let Some(endpoint) = &args.router_endpoint {
        roster.router_endpoint = endpoint.clone();
    }
    if let Some(dir) = &args.install_dir {
        roster.install_dir = Some(dir.clone());
    }
    roster.validate()?;
    if roster.identities().is_empty() {
        bail!("the roster names no identity: give --trolleys, --planners, ... or --roster");
    }
    Ok(roster)
}

fn init(args: InitArgs) -> anyhow::Result<()> {
    let roster = roster_from(&args)?;
    let layout = create(&args.out, &roster, args.validity.valid_days)?;
    println!(
        "{} identities in {}; CA ca.pem, router router.json5, one <kind>-<id>.json5 each.",
        roster.identities().len(),
        layout.dir.display()
    );
    println!("Run `glasshouse router --zenoh-config router.json5` and give every binary its own config with --zenoh-config.");
    Ok(())
}

/// Writes a new PKI for `roster` into `out` (created; must not hold a CA yet): the CA, the
/// router's and every identity's key and certificate, the roster and every config.
pub fn create(out: &Path, roster: &Roster, valid_days: u32) -> anyhow::Result<Layout> {
    let validity = Validity { valid_days };
    std::fs::create_dir_all(out).with_context(|| out.display().to_string())?;
    let layout = Layout::new(&std::fs::canonicalize(out)?);
    if layout.ca_key().exists() {
        bail!(
            "{} already holds a CA; use `glasshouse secure issue` to add identities",
            layout.dir.display()
        );
    }
    let ca_key = KeyPair::generate()?;
    let ca_params = ca_params(validity);
    let ca_cert = ca_params.self_signed(&ca_key)?;
    write_key(&layout.ca_key(), &ca_key)?;
    write_file(&layout.ca_cert(), &ca_cert.pem())?;
    let ca = Issuer::new(ca_params, ca_key);
    let router = leaf_params(
        ROUTER,
        roster.router_hosts.clone(),
        ExtendedKeyUsagePurpose::ServerAuth,
        validity,
    )?;
    write_signed(&layout, ROUTER, router, &ca)?;
    for identity in roster.identities() {
        write_identity(&layout, roster, &identity, &ca, validity)?;
    }
    write_roster_and_router(&layout, roster)?;
    Ok(layout)
}

fn issue(args: IssueArgs) -> anyhow::Result<()> {
    let layout = Layout::new(
        &std::fs::canonicalize(&args.out).with_context(|| args.out.display().to_string())?,
    );
    let identity = args.identity.identity()?;
    let mut roster = Roster::parse(&read(&layout.roster())?)
        .with_context(|| layout.roster().display().to_string())?;
    roster.add(&identity)?;
    let ca_key = KeyPair::from_pem(&read(&layout.ca_key())?).context("the CA key")?;
    let ca = Issuer::from_ca_cert_pem(&read(&layout.ca_cert())?, ca_key).context("the CA")?;
    write_identity(&layout, &roster, &identity, &ca, args.validity)?;
    write_roster_and_router(&layout, &roster)?;
    let name = identity.common_name();
    println!(
        "issued {name}: {}; router.json5's ACL now includes it.",
        layout.config(&name).display()
    );
    println!("Restart the router to apply the new ACL (it reads router.json5 only at start).");
    Ok(())
}

fn validity_window(params: &mut CertificateParams, validity: Validity) {
    let now = time::OffsetDateTime::now_utc();
    // A day back, so a clock a little behind still accepts a fresh certificate.
    params.not_before = now - time::Duration::days(1);
    params.not_after = now + time::Duration::days(i64::from(validity.valid_days));
}

fn named(common_name: &str) -> DistinguishedName {
    let mut name = DistinguishedName::new();
    name.push(DnType::CommonName, common_name);
    name.push(DnType::OrganizationName, "glasshouse");
    name
}

fn ca_params(validity: Validity) -> CertificateParams {
    let mut params = CertificateParams::default();
    params.distinguished_name = named("glasshouse-ca");
    params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    validity_window(&mut params, validity);
    params
}

fn leaf_params(
    common_name: &str,
    alt_names: Vec<String>,
    usage: ExtendedKeyUsagePurpose,
    validity: Validity,
) -> anyhow::Result<CertificateParams> {
    let mut params = CertificateParams::new(alt_names)?;
    params.distinguished_name = named(common_name);
    params.is_ca = IsCa::ExplicitNoCa;
    params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
    params.extended_key_usages = vec![usage];
    params.use_authority_key_identifier_extension = true;
    validity_window(&mut params, validity);
    Ok(params)
}

/// A new key and its certificate signed by `ca`, as `<stem>.key` (0600) and `<stem>.pem`.
fn write_signed(
    layout: &Layout,
    stem: &str,
    params: CertificateParams,
    ca: &Issuer<'_, KeyPair>,
) -> anyhow::Result<()> {
    let key = KeyPair::generate()?;
    let cert = params.signed_by(&key, ca)?;
    write_key(&layout.key(stem), &key)?;
    write_file(&layout.cert(stem), &cert.pem())
}

fn write_identity(
    layout: &Layout,
    roster: &Roster,
    identity: &Identity,
    ca: &Issuer<'_, KeyPair>,
    validity: Validity,
) -> anyhow::Result<()> {
    let name = identity.common_name();
    let params = leaf_params(
        &name,
        Vec::new(),
        ExtendedKeyUsagePurpose::ClientAuth,
        validity,
    )?;
    write_signed(layout, &name, params, ca)?;
    let config = client_config(roster, identity, &roster.installed(layout));
    write_file(
        &layout.config(&name),
        &config_text(&format!("Zenoh client config of {name}"), &config),
    )
}

fn write_roster_and_router(layout: &Layout, roster: &Roster) -> anyhow::Result<()> {
    write_file(&layout.roster(), &roster.to_text())?;
    let config = router_config(roster, &roster.installed(layout))?;
    write_file(
        &layout.config(ROUTER),
        &config_text("Zenoh config of the router: mTLS listener and ACL", &config),
    )
}

fn read(path: &Path) -> anyhow::Result<String> {
    std::fs::read_to_string(path).with_context(|| path.display().to_string())
}

fn write_file(path: &Path, text: &str) -> anyhow::Result<()> {
    std::fs::write(path, text).with_context(|| path.display().to_string())
}

/// Writes a private key readable by its owner only; an existing key is never replaced.
fn write_key(path: &Path, key: &KeyPair) -> anyhow::Result<()> {
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let mut file = options
        .open(path)
        .with_context(|| format!("{} (keys are never overwritten)", path.display()))?;
    file.write_all(key.serialize_pem().as_bytes())
        .with_context(|| path.display().to_string())
}
