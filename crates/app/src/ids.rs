//! Ids of new objects (maps, localizations, trips): random and time-ordered, generated here,
//! in the use-case layer, so every storage engine follows one rule.
//!
//! An id is a 63-bit number (it fits PostgreSQL's `BIGINT`): the milliseconds since
//! 2020-01-01 UTC in its top 41 bits (until 2089), 22 random bits (from the operating system)
//! below. Ids therefore cannot be enumerated (guessing one means guessing 22 random bits per
//! millisecond of creation time), while listings that go newest first with an exclusive
//! `before` id keep working, and the small sequential ids of older stores (engine counters,
//! far below 2^41) stay readable and list as the oldest. Within one process ids strictly
//! increase, even when the clock steps back; two processes that draw the same id in the same
//! millisecond are caught by the engine (`StoreError::IdTaken`) and the use case draws again.
//!
//! On the wire an id is 16 lowercase hex digits, as before.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

use std::future::Future;

use super::error::{AppError, AppResult};
use crate::store::{StoreError, StoreResult};

/// 2020-01-01T00:00:00Z in milliseconds since the Unix epoch.
const EPOCH_MS: u64 = 1_577_836_800_000;
/// Random low bits of an id.
const RANDOM_BITS: u32 = 22;
/// Time bits above them (41 + 22 = 63: the top bit stays 0).
const TIME_BITS: u32 = 41;

/// The last id this process handed out.
static LAST: AtomicU64 = AtomicU64::new(0);

/// A new id: random, after every id this process generated before.
pub fn new_id() -> AppResult<u64> {
    let random = getrandom::u64()
        .map_err(|e| AppError::Internal(format!("no randomness from the OS: {e}")))?;
    let now = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX));
    Ok(next_after(&LAST, now, random))
}

/// Draws of an id for one new object before giving up (a collision needs two processes to
/// draw the same 22 random bits in the same millisecond).
const DRAWS: usize = 4;

/// Creates a new object with `create`, under a new id set by `set_id`, drawing again while the
/// engine answers [`StoreError::IdTaken`].
pub(crate) async fn create_with_new_id<N, T, Fut>(
    mut new: N,
    set_id: fn(&mut N, u64),
    create: impl Fn(N) -> Fut,
) -> AppResult<T>
where
    N: Clone,
    Fut: Future<Output = StoreResult<T>>,
{
    for _ in 1..DRAWS {
        set_id(&mut new, new_id()?);
        let result = create(new.clone()).await;
        if !matches!(result, Err(StoreError::IdTaken(_))) {
            return Ok(result?);
        }
    }
    set_id(&mut new, new_id()?);
    Ok(create(new).await?)
}

/// The id for time `now_ms` and random bits `random`, strictly above the one in `last`
/// (which it then holds).
fn next_after(last: &AtomicU64, now_ms: u64, random: u64) -> u64 {
    let time = now_ms.saturating_sub(EPOCH_MS) & ((1 << TIME_BITS) - 1);
    let low = random & ((1 << RANDOM_BITS) - 1);
    let candidate = (time << RANDOM_BITS) | low;
    let mut prev = last.load(Ordering::Relaxed);
    loop {
        // Same millisecond (or a clock that stepped back): move on by a random step, so the
        // next id is still not "previous + 1".
        let id = if candidate > prev {
            candidate
        } else {
            prev + 1 + (random >> 48)
        };
        match last.compare_exchange_weak(prev, id, Ordering::Relaxed, Ordering::Relaxed) {
            Ok(_) => return id,
            Err(now) => prev = now,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 2026-11-23T12:00:00Z.
    const T: u64 = 1_795_435_200_000;

    #[test]
    fn ids_carry_their_time_and_random_bits() {
        let last = AtomicU64::new(0);
        let a = next_after(&last, T, 0x3f_ffff);
        assert_eq!(a >> RANDOM_BITS, T - EPOCH_MS);
        assert_eq!(a & 0x3f_ffff, 0x3f_ffff);
        assert!(a < 1 << 63, "fits a signed 64-bit integer");
        // A later millisecond gives a larger id whatever the random bits.
        let b = next_after(&last, T + 1, 0);
        assert!(b > a);
        // Old sequential ids (engine counters) sort before every new one.
        assert!(a > 1 << 40);
    }

    #[test]
    fn ids_strictly_increase_in_one_millisecond_and_when_the_clock_steps_back() {
        let last = AtomicU64::new(0);
        let mut prev = 0;
        for (k, now) in [T, T, T, T - 5_000, T].into_iter().enumerate() {
            let id = next_after(&last, now, (k as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
            assert!(id > prev, "{id} after {prev}");
            prev = id;
        }
    }

    #[test]
    fn ids_from_the_os_are_distinct_and_increasing() {
        let ids: Vec<u64> = (0..1000).map(|_| new_id().unwrap()).collect();
        assert!(ids.windows(2).all(|w| w[0] < w[1]));
        // Not a counter: consecutive ids differ by more than 1 most of the time.
        let gaps_of_one = ids.windows(2).filter(|w| w[1] - w[0] == 1).count();
        assert!(gaps_of_one < 10, "{gaps_of_one} of 999 gaps were 1");
    }
}
