//! Who makes a request, as far as the use cases care: the name of the API key and whether it
//! is an admin. The front end authenticates; this layer keeps the one rule that needs the
//! caller beyond its role: a trip is extended and closed only by the key that opened it, or by
//! an admin ([`Caller::may_change`]). Without access control (keyless loopback serving) there
//! is no caller and no owner, and nothing is refused here.

use crate::error::{AppError, AppResult};
use crate::model::TripRecord;

/// An authenticated caller.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Caller {
    /// The key's name (from the key file; never the key).
    pub name: String,
    /// Whether the key has the admin role.
    pub admin: bool,
}

impl Caller {
    /// Whether `caller` may post frames to `trip` or close it: always without access control
    /// (`None`), for an admin, for the key that opened it, and for any key when the trip has
    /// no owner (opened without keys, or stored before owners were kept).
    pub fn may_change(caller: Option<&Caller>, trip: &TripRecord) -> AppResult<()> {
        match (caller, &trip.owner) {
            (Some(c), Some(owner)) if !c.admin && c.name != *owner => {
                Err(AppError::NotTripOwner(format!(
                    "trip `{:016x}` was opened by key `{owner}`; key `{}` may read it but only \
                     `{owner}` or an admin may post frames to it or close it",
                    trip.id, c.name
                )))
            }
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use seasonloc_core::trip::TripParams;

    fn trip(owner: Option<&str>) -> TripRecord {
        TripRecord {
            id: 7,
            map_id: 1,
            created_ms: 0,
            closed_ms: None,
            frame_count: 0,
            reference_count: 3,
            status: None,
            params: TripParams::default(),
            owner: owner.map(str::to_owned),
        }
    }

    fn key(name: &str, admin: bool) -> Caller {
        Caller {
            name: name.into(),
            admin,
        }
    }

    #[test]
    fn only_the_opener_or_an_admin_changes_an_owned_trip() {
        let owned = trip(Some("vehicle-a"));
        assert!(Caller::may_change(Some(&key("vehicle-a", false)), &owned).is_ok());
        assert!(Caller::may_change(Some(&key("ops", true)), &owned).is_ok());
        assert!(Caller::may_change(None, &owned).is_ok());
        let e = Caller::may_change(Some(&key("vehicle-b", false)), &owned).unwrap_err();
        assert_eq!(e.code(), crate::error::ErrorCode::Forbidden);
        assert!(e.to_string().contains("vehicle-a"), "{e}");
        assert!(Caller::may_change(Some(&key("vehicle-b", false)), &trip(None)).is_ok());
    }
}
