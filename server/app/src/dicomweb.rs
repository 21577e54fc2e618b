//! A PACS as a dataset source, over DICOMweb.
//!
//! - QIDO-RS `GET {base}/series` lists the series at start-up; each is a dataset named
//!   `dicomweb/<SeriesInstanceUID>` (no patient data in the name).
//! - Opening one: QIDO-RS lists its instances, WADO-RS fetches them, a few at a time (as stored:
//!   `transfer-syntax=*`, the DICOM loader decodes what it supports) into a private temporary
//!   folder, reporting progress per instance; the series loader then reads that folder.
//! - Credentials come from a file (`user:password`, or `Bearer <token>`); they are sent as an
//!   `Authorization` header and never logged or shown (`Debug` redacts them).

use std::io::Read;
use std::path::Path;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use base64::Engine as _;

/// Largest body accepted for one instance (a multi-frame enhanced CT can be large).
const MAX_INSTANCE_BYTES: u64 = 2 << 30;
/// Largest QIDO-RS answer accepted.
const MAX_LISTING_BYTES: u64 = 64 << 20;
/// One request may take this long (a large instance over a slow link).
const REQUEST_TIMEOUT: Duration = Duration::from_secs(300);
/// Instances fetched at once: a PACS far away answers each request after a round trip.
const FETCH_THREADS: usize = 4;

#[derive(Debug, thiserror::Error)]
pub enum DicomWebError {
    #[error("DICOMweb credentials file {path}: {reason}")]
    Credentials { path: String, reason: String },
    #[error("DICOMweb {what}: {source}")]
    Http {
        what: String,
        #[source]
        source: Box<ureq::Error>,
    },
    #[error("DICOMweb {what}: {reason}")]
    Unexpected { what: String, reason: String },
    #[error("keeping a fetched instance: {0}")]
    Io(#[from] std::io::Error),
}

/// A series the PACS offers.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RemoteSeries {
    pub study: String,
    pub series: String,
    pub modality: String,
    /// From QIDO-RS (`NumberOfSeriesRelatedInstances`), 0 when the PACS does not say.
    pub instances: u32,
}

impl RemoteSeries {
    pub fn dataset_name(&self) -> String {
        format!("dicomweb/{}", self.series)
    }
}

/// A DICOMweb endpoint (`https://pacs.example.org/dicom-web`).
pub struct DicomWeb {
    base: String,
    authorization: Option<String>,
    agent: ureq::Agent,
}

impl std::fmt::Debug for DicomWeb {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DicomWeb")
            .field("base", &self.base)
            .field(
                "authorization",
                &self.authorization.as_ref().map(|_| "<redacted>"),
            )
            .finish()
    }
}

/// The `Authorization` header value from a credentials file: its first line that is neither
/// blank nor a `#` comment, `user:password` (Basic) or `Bearer <token>`.
pub fn read_credentials(path: &Path) -> Result<String, DicomWebError> {
    let bad = |reason: &str| DicomWebError::Credentials {
        path: path.display().to_string(),
        reason: reason.to_owned(),
    };
    let text = std::fs::read_to_string(path).map_err(|e| bad(&e.to_string()))?;
    let line = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .ok_or_else(|| {
            bad("no credentials in it (expected `user:password` or `Bearer <token>`)")
        })?;
    if let Some(token) = line.strip_prefix("Bearer ") {
        let token = token.trim();
        if token.is_empty() {
            return Err(bad("`Bearer` without a token"));
        }
        return Ok(format!("Bearer {token}"));
    }
    if !line.contains(':') {
        return Err(bad("expected `user:password` or `Bearer <token>`"));
    }
    Ok(format!(
        "Basic {}",
        base64::engine::general_purpose::STANDARD.encode(line)
    ))
}

/// The first `Value` of a DICOM JSON attribute, as text (strings and numbers alike).
fn json_value(item: &serde_json::Value, tag: &str) -> Option<String> {
    let value = item.get(tag)?.get("Value")?.get(0)?;
    match value {
        serde_json::Value::String(s) => Some(s.clone()),
        serde_json::Value::Number(n) => Some(n.to_string()),
        _ => None,
    }
}

/// A UID as it may appear in a URL path: digits and dots only.
fn check_uid(uid: &str) -> Result<&str, DicomWebError> {
    if !uid.is_empty() && uid.len() <= 64 && uid.bytes().all(|b| b.is_ascii_digit() || b == b'.') {
        Ok(uid)
    } else {
        Err(DicomWebError::Unexpected {
            what: "listing".into(),
            reason: format!("`{uid}` is not a DICOM UID"),
        })
    }
}

/// The parts of a `multipart/related` body.
fn multipart_parts<'a>(content_type: &str, body: &'a [u8]) -> Result<Vec<&'a [u8]>, String> {
    let boundary = content_type
        .split(';')
        .map(str::trim)
        .find_map(|p| p.strip_prefix("boundary="))
        .map(|b| b.trim_matches('"'))
        .filter(|b| !b.is_empty())
        .ok_or_else(|| format!("no boundary in `{content_type}`"))?;
    let delimiter = format!("--{boundary}");
    let finder = memchr::memmem::Finder::new(delimiter.as_bytes());
    let starts: Vec<usize> = finder.find_iter(body).collect();
    let mut parts = Vec::new();
    for pair in starts.windows(2) {
        let part = &body[pair[0] + delimiter.len()..pair[1]];
        // Headers end at the first blank line; the content ends before the CRLF that precedes
        // the next delimiter.
        let Some(headers_end) = memchr::memmem::find(part, b"\r\n\r\n") else {
            return Err("a part without headers".into());
        };
        let content = &part[headers_end + 4..];
        parts.push(content.strip_suffix(b"\r\n").unwrap_or(content));
    }
    Ok(parts)
}

impl DicomWeb {
    /// `base` is the DICOMweb root (QIDO-RS and WADO-RS under it); `authorization` the header
    /// value (`read_credentials`).
    pub fn new(base: &str, authorization: Option<String>) -> Result<Self, DicomWebError> {
        let base = base.trim_end_matches('/').to_owned();
        if !(base.starts_with("http://") || base.starts_with("https://")) {
            return Err(DicomWebError::Unexpected {
                what: "URL".into(),
                reason: format!("`{base}` is not an http:// or https:// URL"),
            });
        }
        let agent = ureq::Agent::config_builder()
            .timeout_global(Some(REQUEST_TIMEOUT))
            .build()
            .into();
        Ok(Self {
            base,
            authorization,
            agent,
        })
    }

    fn get(
        &self,
        what: &str,
        path: &str,
        accept: &str,
        limit: u64,
    ) -> Result<(String, Vec<u8>), DicomWebError> {
        let url = format!("{}/{path}", self.base);
        let mut request = self.agent.get(&url).header("Accept", accept);
        if let Some(authorization) = &self.authorization {
            request = request.header("Authorization", authorization);
        }
        let http = |source: ureq::Error| DicomWebError::Http {
            what: what.to_owned(),
            source: Box::new(source),
        };
        let mut response = request.call().map_err(http)?;
        let content_type = response
            .headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok())
            .unwrap_or_default()
            .to_owned();
        let mut body = Vec::new();
        response
            .body_mut()
            .with_config()
            .limit(limit)
            .reader()
            .read_to_end(&mut body)?;
        Ok((content_type, body))
    }

    fn listing(&self, what: &str, path: &str) -> Result<Vec<serde_json::Value>, DicomWebError> {
        let (_, body) = self.get(what, path, "application/dicom+json", MAX_LISTING_BYTES)?;
        if body.is_empty() {
            return Ok(Vec::new()); // 204: nothing matches
        }
        serde_json::from_slice(&body).map_err(|e| DicomWebError::Unexpected {
            what: what.to_owned(),
            reason: format!("not a DICOM JSON array: {e}"),
        })
    }

    /// Every series the endpoint lists (QIDO-RS).
    pub fn list_series(&self) -> Result<Vec<RemoteSeries>, DicomWebError> {
        let items = self.listing(
            "series listing",
            "series?includefield=00080060&includefield=00201209",
        )?;
        let mut series = Vec::new();
        for item in &items {
            let (Some(study), Some(uid)) =
                (json_value(item, "0020000D"), json_value(item, "0020000E"))
            else {
                continue;
            };
            series.push(RemoteSeries {
                study: check_uid(&study)?.to_owned(),
                series: check_uid(&uid)?.to_owned(),
                modality: json_value(item, "00080060").unwrap_or_default(),
                instances: json_value(item, "00201209")
                    .and_then(|n| n.parse().ok())
                    .unwrap_or(0),
            });
        }
        Ok(series)
    }

    /// Fetches every instance of `series` into `folder` (WADO-RS, one request per instance,
    /// `FETCH_THREADS` at a time), calling `progress(done, total)` after each, in order of
    /// completion. Returns the number of files written.
    pub fn fetch_series(
        &self,
        series: &RemoteSeries,
        folder: &Path,
        progress: &(dyn Fn(u32, u32) + Sync),
    ) -> Result<u32, DicomWebError> {
        let prefix = format!("studies/{}/series/{}", series.study, series.series);
        let instances: Vec<String> = self
            .listing("instance listing", &format!("{prefix}/instances"))?
            .iter()
            .filter_map(|item| json_value(item, "00080018"))
            .collect();
        let total = instances.len() as u32;
        if total == 0 {
            return Err(DicomWebError::Unexpected {
                what: "instance listing".into(),
                reason: "the series has no instances".into(),
            });
        }
        progress(0, total);
        let fetch_one = |i: usize| -> Result<u32, DicomWebError> {
            let what = format!("instance {} of {total}", i + 1);
            let (content_type, body) = self.get(
                &what,
                &format!("{prefix}/instances/{}", check_uid(&instances[i])?),
                "multipart/related; type=\"application/dicom\"; transfer-syntax=*",
                MAX_INSTANCE_BYTES,
            )?;
            let parts = multipart_parts(&content_type, &body)
                .map_err(|reason| DicomWebError::Unexpected { what, reason })?;
            for (k, part) in parts.iter().enumerate() {
                std::fs::write(folder.join(format!("{i:06}-{k}.dcm")), part)?;
            }
            Ok(parts.len() as u32)
        };
        let next = AtomicUsize::new(0);
        // Files written and instances done, counted under one lock so progress only grows.
        let counts = Mutex::new((0u32, 0u32));
        let failure: Mutex<Option<DicomWebError>> = Mutex::new(None);
        std::thread::scope(|scope| {
            for _ in 0..FETCH_THREADS.min(instances.len()) {
                scope.spawn(|| {
                    loop {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        if i >= instances.len() || failure.lock().map_or(true, |f| f.is_some()) {
                            return;
                        }
                        match fetch_one(i) {
                            Ok(files) => {
                                if let Ok(mut counts) = counts.lock() {
                                    counts.0 += files;
                                    counts.1 += 1;
                                    progress(counts.1, total);
                                }
                            }
                            Err(e) => {
                                if let Ok(mut failure) = failure.lock() {
                                    failure.get_or_insert(e);
                                }
                                return;
                            }
                        }
                    }
                });
            }
        });
        if let Some(e) = failure.into_inner().ok().flatten() {
            return Err(e);
        }
        Ok(counts.into_inner().map_or(0, |c| c.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn multipart_parts_are_split_at_the_boundary() {
        let body = b"--abc\r\nContent-Type: application/dicom\r\n\r\nDICM-one\r\n--abc\r\nContent-Type: application/dicom\r\nContent-Length: 3\r\n\r\ntwo\r\n--abc--\r\n";
        let parts = multipart_parts(
            "multipart/related; type=\"application/dicom\"; boundary=\"abc\"",
            body,
        )
        .unwrap();
        assert_eq!(parts, vec![&b"DICM-one"[..], &b"two"[..]]);
        assert!(multipart_parts("multipart/related", body).is_err());
    }

    #[test]
    fn credentials_become_an_authorization_header_and_stay_out_of_debug() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("pacs");
        std::fs::write(&file, "# PACS account\n\nradiology:s3cret\n").unwrap();
        let header = read_credentials(&file).unwrap();
        assert_eq!(header, "Basic cmFkaW9sb2d5OnMzY3JldA==");
        std::fs::write(&file, "Bearer abc.def\n").unwrap();
        assert_eq!(read_credentials(&file).unwrap(), "Bearer abc.def");
        std::fs::write(&file, "nocolon\n").unwrap();
        let error = read_credentials(&file).unwrap_err().to_string();
        assert!(
            !error.contains("nocolon"),
            "the secret is not echoed: {error}"
        );
        let source = DicomWeb::new("http://127.0.0.1:1/dicom-web/", Some(header)).unwrap();
        let shown = format!("{source:?}");
        assert!(
            !shown.contains("cmFk") && shown.contains("redacted"),
            "{shown}"
        );
        assert!(DicomWeb::new("ftp://x", None).is_err());
    }

    #[test]
    fn uids_with_anything_but_digits_and_dots_are_refused() {
        assert!(check_uid("1.2.840.10008").is_ok());
        assert!(check_uid("1.2/../../x").is_err());
        assert!(check_uid("").is_err());
    }
}
