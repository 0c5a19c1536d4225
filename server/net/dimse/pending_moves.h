// The C-MOVE retrievals in progress (retrieve.h, peers with `retrieve:
// move`), as the DICOM listener sees them.
//
// A C-MOVE asks the peer to send the series to a move destination: our own
// listener (our first AE title). The peer opens association(s) of its own,
// calling as its AE title, and C-STOREs the instances. While the move is
// pending, the listener (association.cc) looks every received instance up
// here by (calling AE title, Study Instance UID, Series Instance UID) before
// the series assembler sees it: a match goes into the move's folder (the
// job's upload folder) and never reaches the rules; no match goes on to the
// assembler as any other instance.
//
// Contract:
// - One pending move per key: while another move of the same series from
//   the same peer is in progress, Register waits for it to end (two jobs
//   pulling the same series run their moves one after the other), as long
//   as its `may_wait` says OK (polled every 200 ms; without one it fails at
//   once with FAILED_PRECONDITION).
// - Move::Accept writes durably (fsync, rename, fsync of the folder: the
//   same helpers as the assembler, series_assembler.h) a received file that
//   already passed the bounded scan, within max_instances / max_bytes (past
//   them: RESOURCE_EXHAUSTED, the file not kept, the move failed).
// - A move that ended (Close) stays in the registry as closed for
//   kClosedGrace: instances of it that arrive late (after a timeout or a
//   failure) are refused (FAILED_PRECONDITION), never handed to the rules.
//   The listener takes an instance as one of an ended move only when its
//   C-STORE request says it is a C-MOVE sub-operation of ours (its Move
//   Originator AE Title is ours); any other instance of the same series is
//   an ordinary transfer (issue 39: a PACS's push of a series just pulled
//   was refused for the grace period). Registering the same key again
//   replaces it.
// - The retriever waits (WaitSettled) until every association that stored
//   into the move has ended and at least the expected count arrived, or a
//   deadline.
// - Thread-safe; AE titles are compared without surrounding spaces.
#ifndef INTERSLICE_SERVER_NET_DIMSE_PENDING_MOVES_H_
#define INTERSLICE_SERVER_NET_DIMSE_PENDING_MOVES_H_

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace interslice::server::dimse {

class PendingMoves {
 public:
  // How long a closed move keeps refusing its late instances.
  static constexpr std::chrono::minutes kClosedGrace{10};

  class Move {
   public:
    Move(std::string dest_dir, int64_t max_instances, int64_t max_bytes)
        : dest_dir_(std::move(dest_dir)),
          max_instances_(max_instances),
          max_bytes_(max_bytes) {}

    // The listener: `staged` (a received file that passed the bounded
    // scan, `size` bytes) is moved into the folder; it is deleted in every
    // case. `association` is the listener's id of the association that
    // carried it (its end is reported by AssociationEnded).
    absl::Status Accept(uint64_t association, const std::string& staged,
                        int64_t size);
    void AssociationEnded(uint64_t association);

    // The retriever: blocks until no association that stored into the move
    // is open and at least `expected` instances were kept (true), or the
    // deadline (false).
    bool WaitSettled(int64_t expected,
                     std::chrono::steady_clock::time_point deadline);
    int64_t instances();
    int64_t bytes();
    // The first refusal (limits, disk), OK if none.
    absl::Status error();
    // Deletes the files the move kept (a failed move leaves nothing).
    void RemoveKept();
    // Whether the move has ended (Close).
    bool ended();

   private:
    friend class PendingMoves;
    std::mutex mu_;
    std::condition_variable cv_;
    const std::string dest_dir_;
    const int64_t max_instances_, max_bytes_;
    int64_t instances_ = 0, bytes_ = 0;
    std::set<uint64_t> open_;
    std::vector<std::string> kept_;
    absl::Status error_;
    bool closed_ = false;
    std::chrono::steady_clock::time_point closed_at_;
  };

  // A move of the series from the peer calling as `calling_ae` into
  // `dest_dir` (which must exist). While the same series from the same peer
  // is being moved, waits for that move to end while `may_wait` returns OK
  // (its other status is returned: the job was cancelled, or waited long
  // enough); a null `may_wait` does not wait (FAILED_PRECONDITION).
  absl::StatusOr<std::shared_ptr<Move>> Register(
      const std::string& calling_ae, const std::string& study_uid,
      const std::string& series_uid, const std::string& dest_dir,
      int64_t max_instances, int64_t max_bytes,
      const std::function<absl::Status()>& may_wait = nullptr);
  // The move ended (successfully or not): later instances are refused.
  void Close(const std::shared_ptr<Move>& move);

  // Whether a move (pending or closed) from this calling AE is known: the
  // listener reads an instance's UIDs before the assembler only then.
  bool Expects(const std::string& calling_ae);
  // The move of this series from this caller, or null.
  std::shared_ptr<Move> Find(const std::string& calling_ae,
                             const std::string& study_uid,
                             const std::string& series_uid);

 private:
  using Key = std::tuple<std::string, std::string, std::string>;
  // With mu_ held: forgets closed moves past their grace.
  void Expire();

  std::mutex mu_;
  std::map<Key, std::shared_ptr<Move>> moves_;
};

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_PENDING_MOVES_H_
