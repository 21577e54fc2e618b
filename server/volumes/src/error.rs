//! Error type shared by every loader.

use std::path::PathBuf;

/// Everything that can go wrong while loading, decoding or generating a volume.
///
/// Every message names the file (when there is one) and says what was expected and what was
/// found.
#[derive(Debug, thiserror::Error)]
pub enum VolumeError {
    /// The operating system refused an operation on a file or directory.
    #[error("I/O error on {}: {what}: {source}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What was being done (e.g. "opening the file").
        what: String,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The file is malformed: a header field is missing or invalid, data is truncated, etc.
    #[error("{}: {msg}", path.display())]
    Format {
        /// The offending file.
        path: PathBuf,
        /// What is wrong, with expected and found values.
        msg: String,
    },
    /// The file is well-formed but uses a feature this crate does not implement.
    #[error("{}: unsupported: {msg}", path.display())]
    Unsupported {
        /// The offending file.
        path: PathBuf,
        /// Which feature, and what is supported instead.
        msg: String,
    },
    /// The declared volume is larger than [`crate::MAX_VOXELS`]; nothing was allocated.
    #[error(
        "{}: volume too large: {dims:?} = {voxels} voxels, the limit is {limit} voxels",
        path.display()
    )]
    TooLarge {
        /// The offending file.
        path: PathBuf,
        /// The declared dimensions (as wide integers, so that overflowing values show).
        dims: [u64; 3],
        /// Their product (saturated at `u64::MAX`).
        voxels: u64,
        /// [`crate::MAX_VOXELS`].
        limit: u64,
    },
    /// The path's format could not be recognised from its name or its first bytes.
    #[error(
        "{}: unknown volume format: expected a directory (DICOM series), .dcm, .nrrd, .nhdr, \
         .nii, .nii.gz or .vti",
        path.display()
    )]
    UnknownFormat {
        /// The path.
        path: PathBuf,
    },
    /// No procedural phantom has this name.
    #[error("unknown phantom {name:?}: known phantoms are {known}")]
    UnknownPhantom {
        /// The requested name.
        name: String,
        /// Comma-separated list of valid names.
        known: String,
    },
    /// A caller-supplied argument is invalid (phantom size, raw dims, ...).
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
}

impl VolumeError {
    pub(crate) fn io(
        path: impl Into<PathBuf>,
        what: impl Into<String>,
        source: std::io::Error,
    ) -> Self {
        VolumeError::Io {
            path: path.into(),
            what: what.into(),
            source,
        }
    }

    pub(crate) fn format(path: impl Into<PathBuf>, msg: impl Into<String>) -> Self {
        VolumeError::Format {
            path: path.into(),
            msg: msg.into(),
        }
    }

    pub(crate) fn unsupported(path: impl Into<PathBuf>, msg: impl Into<String>) -> Self {
        VolumeError::Unsupported {
            path: path.into(),
            msg: msg.into(),
        }
    }
}
