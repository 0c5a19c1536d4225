// The intake: the one way received DICOM instances enter the node, whatever
// the door: a DIMSE association (server/net/dimse/association.h) or a
// STOW-RS request (server/net/dicomweb/stow.h). A transfer is one
// association or one request; each instance of it is staged by the door
// (written as it arrives) and handed over whole, and the transfer's end
// says whether it ended whole. What the node makes of them (grouping into
// series, completeness, rules, jobs) is the intake's business and the same
// for every door: docs/dicom-node.md, "Completeness".
//
// (Jobs enter the engine by other doors: a gRPC upload or a pull from a
// peer names its own files, and goes to JobManager::Admit; the node's own
// jobs, made of complete series, too.)
#ifndef INTERSLICE_SERVER_NODE_INTAKE_H_
#define INTERSLICE_SERVER_NODE_INTAKE_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "server/node/dataset_scan.h"

namespace interslice::server::node {

// The door a transfer comes through. It decides what a transfer that ended
// whole proves about a series (docs/dicom-node.md, "Completeness"): an
// association may hold a whole series (a rule's complete_on_release), a
// STOW-RS request is only part of a sender's upload (clients send one
// instance or a few per request), so a rule must opt into one job per
// request (complete_on_request).
enum class Door { kAssociation, kStowRequest };

class Intake {
 public:
  virtual ~Intake() = default;

  // A transfer begins: an association was accepted (calling and called AE
  // titles) or a request authenticated (its sender's name, and the AE title
  // the request stores as). Returns its id for the calls below.
  virtual uint64_t BeginTransfer(Door door, const std::string& calling_ae,
                                 const std::string& called_ae) = 0;

  // A fresh path for an instance about to be received; the door writes the
  // instance there (its meta group, then the data set as received).
  virtual std::string StagingPath() = 0;
  // The most bytes one instance may have: a door cuts off a reception that
  // passes it while it streams in.
  virtual int64_t max_instance_bytes() const = 0;
  // The bounded scan's limits every received instance passes.
  virtual const DatasetScanLimits& scan_limits() const = 0;

  // Blocking. Takes the staged instance (deleted in every case) into its
  // series; OK means kept (fsynced), and only then may the door answer
  // success. `received_bytes`: the data set's bytes as they arrived (-1:
  // unknown). RESOURCE_EXHAUSTED for limits, quota and a full disk;
  // INVALID_ARGUMENT for an instance that is not well-formed or lacks its
  // UIDs; UNIMPLEMENTED for a SOP class the node does not store
  // (StorableSopClass). Every refusal makes what the instance belonged to
  // incomplete.
  // Returns the key of the series it joined.
  virtual absl::StatusOr<std::string> AddInstance(uint64_t transfer,
                                                  const std::string& staged,
                                                  int64_t received_bytes) = 0;

  // An instance of `transfer` was refused before its series was known (the
  // door could not even stage it): every series of the transfer is
  // incomplete.
  virtual void InstanceRefused(uint64_t transfer) = 0;

  // The transfer ended: `whole` when it ended as its protocol says a
  // transfer ends well (an A-RELEASE; a request body that reached its close
  // delimiter with nothing refused), false otherwise (aborted, cut off,
  // lost, timed out, the server stopping).
  virtual void EndTransfer(uint64_t transfer, bool whole) = 0;
};

// The storage SOP classes the node takes (UIDs), the same at every door:
// the DIMSE listener offers exactly these, STOW-RS refuses any other
// instance (Failure Reason 0x0122), AddInstance refuses any other.
const std::vector<std::string>& StorableSopClasses();
bool StorableSopClass(const std::string& sop_class_uid);

}  // namespace interslice::server::node

#endif  // INTERSLICE_SERVER_NODE_INTAKE_H_
