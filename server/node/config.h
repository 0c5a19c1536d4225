// The DICOM node's configuration files: the peers file (--dicom-peers) and
// the rules file (--rules). Both are YAML; JSON is valid YAML, so tools may
// write either. docs/dicom-node.md documents them with examples
// (docs/examples/peers.yaml, rules.yaml, parsed by the tests).
//
// Peers file:
//   accept_unknown_callers: false     # optional; default false
//   peers:
//     - {name: orthanc, ae_title: ORTHANC, host: 127.0.0.1, port: 4242,
//        tls: false,                  # port default 104, tls default false
//        max_associations: 4,         # optional, 1-16: deliveries to this
//                                     # peer in parallel associations
//        allowed_sources: [127.0.0.1, 10.20.0.0/16],
//                                     # optional: the addresses or networks
//                                     # associations calling as this AE
//                                     # title may come from
//        retrieve: get}               # optional, get (default) | move: how
//                                     # a series is pulled (C-GET, or
//                                     # C-MOVE to our listener)
//     - {name: cloud, type: dicomweb,  # type: dimse (default) | dicomweb
//        url: https://pacs.example/dicom-web,   # base URL (http or https)
//        bearer_token_file: /etc/interslice/cloud.token,  # or:
//        # basic_user: interslice, basic_password_file: /etc/.../pw,
//        client_certificate: c.pem, client_key: k.pem,  # mutual TLS
//        ca_certificates: ca.pem,     # https: CAs of the server
//        max_associations: 4}         # STOW-RS requests in parallel
//   A DICOMweb peer has no ae_title, host, port, tls, allowed_sources or
//   retrieve
//   (errors if given); a DIMSE peer none of the DICOMweb keys. The files
//   must exist and be readable at load time (token and password files not
//   empty); only their paths appear in messages, never their contents.
//
// Rules file:
//   stable_seconds: 30                # optional, > 0 (fractions allowed)
//   rules:                            # ordered; the first match wins
//     - name: ct-bone                 # optional; default "#<1-based index>"
//       match: {modality: CT, series_description: "(?i)head",
//               called_ae: INTERSLICE}
//       job: {threshold: 300, method: direct, output_series: [intensity],
//             seg: true, mesh: [stl]}
//       send_to: [orthanc]            # peer names; optional
//       complete_on_release: false    # optional; see Rule
//       complete_on_request: false    # optional; see Rule
//     - name: fill-seg                # a SEG or RTSTRUCT arrives: fill it
//       match: {modality: SEG}
//       fill: {method: direct, labels: [1, 2], mesh: [stl], volume: [nii]}
//
// Every error is INVALID_ARGUMENT with one line naming the file, the peer or
// rule (name and 1-based index) and the field, e.g.
//   "rules.yaml: rule 'ct-bone' (#1): match.series_description: bad regular
//    expression: missing ): (?i(head"
// Unknown keys and values of the wrong type are errors, never ignored.
#ifndef INTERSLICE_SERVER_NODE_CONFIG_H_
#define INTERSLICE_SERVER_NODE_CONFIG_H_

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "interslice/v1/interslice.pb.h"
#include "server/node/peer.h"

namespace re2 {
class RE2;
}  // namespace re2

namespace interslice::server::node {

struct PeersConfig {
  std::vector<DicomPeer> peers;  // names unique; AE titles trimmed
  // Associations from calling AE titles not listed are rejected at
  // association time unless this is true.
  bool accept_unknown_callers = false;
};

absl::StatusOr<PeersConfig> LoadPeersConfig(const std::string& path);

// "10.0.0.0/8", "192.168.1.7", "fd00::/8", "::1" (no names).
absl::StatusOr<SourceNetwork> ParseSourceNetwork(const std::string& text);
// Whether `address` (numeric IPv4 or IPv6 text, as the listener reports
// peers) lies in `network`.
bool InNetwork(const std::string& address, const SourceNetwork& network);
// The peers only (the sender's view).
absl::StatusOr<std::vector<DicomPeer>> LoadPeersFile(const std::string& path);

// Inclusive range; an absent end is open.
struct ValueRange {
  std::optional<double> min, max;
  bool Contains(double value) const;
};

// What a rule matches on, taken from the received series (the first
// instance's header; counts and spacing over all instances).
struct SeriesFacts {
  std::string modality;                      // (0008,0060)
  std::string series_description;            // (0008,103E)
  std::string protocol_name;                 // (0018,1030)
  std::string body_part;                     // (0018,0015)
  std::optional<double> slice_thickness_mm;  // (0018,0050)
  // Median distance of neighbouring image positions along the slice normal;
  // absent with fewer than two slices or no geometry.
  std::optional<double> slice_spacing_mm;
  int64_t slice_count = 0;  // frames in all instances
  // The first instance is a DICOM SEG or RTSTRUCT (a segmentation drawn on
  // another series): only fill rules match it.
  bool segmentation = false;
  std::string manufacturer;   // (0008,0070)
  std::string image_type;     // (0008,0008), values joined by '\'
  std::string sop_class_uid;  // (0008,0016)
  // Made by interslice: Manufacturer and Manufacturer's Model Name both
  // "interslice", as every object the node writes says (core/dicom_out).
  bool own_result = false;
  std::string calling_ae;
  std::string called_ae;
};

// Each present criterion must hold (AND). Text equality (modality,
// body_part, AE titles) ignores case and surrounding spaces; the regular
// expressions (RE2 syntax, e.g. "(?i)head") are searched anywhere in the
// value (partial match). A range criterion fails when the value is unknown.
//
// The node's own results (SeriesFacts::own_result: a PACS routing rule, or a
// second "send every series" of README, sending them back) match only a
// rule that asks for them with own_results: true (issue 39: results of
// results); own_results: true matches nothing else.
struct RuleMatch {
  std::optional<std::string> modality, body_part, calling_ae, called_ae;
  std::shared_ptr<const re2::RE2> series_description, protocol_name;
  std::optional<ValueRange> slice_thickness_mm, slice_spacing_mm, slice_count;
  // Image Type (its values joined by '\', e.g. "DERIVED\SECONDARY") and
  // Manufacturer as regular expressions; SOP Class UIDs, any of them.
  std::shared_ptr<const re2::RE2> image_type, manufacturer;
  std::vector<std::string> sop_classes;
  bool own_results = false;
  bool Matches(const SeriesFacts& facts) const;
  // The first criterion (in the order above, the own-results guard first)
  // that does not hold, as one phrase naming it and, for modality, body
  // part, AE titles, SOP class and the numeric ranges, the series' value
  // ("modality is 'MR', not 'CT'"); a regular expression's value is never
  // shown (free text may identify a patient). Empty when the match holds.
  // The series' values are raw: callers that log it pass it through
  // LogSafe.
  std::string FirstFailure(const SeriesFacts& facts) const;
  // The criteria as written, without the own-results guard (how a rule's
  // `exclude` reads them): empty when every criterion holds.
  std::string CriteriaFailure(const SeriesFacts& facts) const;
  bool empty() const { return Describe() == "every series"; }
  // The criteria as written, "modality CT, called_ae INTERSLICE", or
  // "every series".
  std::string Describe() const;
};

struct Rule {
  std::string name;  // as written, or "#<index>" when the file gives none
  RuleMatch match;
  // Series this rule does not take although `match` holds: those for which
  // every criterion of `exclude` holds (the same keys as match, e.g.
  // {image_type: "DERIVED"}, {manufacturer: "(?i)acme"}); never empty.
  std::optional<RuleMatch> exclude;
  // The job: the job layer's options (job/options.h: the keys are the
  // command line's option names with '_' for '-'), mapped and checked
  // exactly as every door maps them, with the same defaults (so mesh: stl
  // and volume: nii unless given). send_to is filled from the rule's
  // send_to.
  // A fill rule (key `fill` instead of `job`: the fill options of the same
  // table, e.g. labels, key_slices, method, iterations, factor, mesh; seg
  // defaults to true here) has job.fill set: it matches SEG and RTSTRUCT
  // series only (and other rules never match them); its job fills the
  // segmentation on the series it references, which must be held in the
  // spool (series_assembler.h).
  v1::JobSpec job;
  std::vector<std::string> send_to;
  // true: the series is complete as soon as the association that sent it
  // releases normally (no stable wait): it assumes the sender sends a whole
  // series in one association (a PACS's C-MOVE or "send series" does; a
  // sender that spreads a series over associations makes one job per
  // association). false: only after stable_seconds. DIMSE only.
  bool complete_on_release = false;
  // true: the series is complete as soon as a STOW-RS request that stored
  // into it ends whole: one job per request (MONAI Deploy's gateway makes
  // one workflow per request). false (the default): a series is grouped
  // across requests and completes stable_seconds after its last one.
  bool complete_on_request = false;
};

struct RuleSet {
  std::string path;  // the file, for logs ("rule set <path>")
  double stable_seconds = 30;
  std::vector<Rule> rules;
  // The first rule whose match holds, or null. Only fill rules are tried
  // for a segmentation (facts.segmentation), only the others for a series.
  const Rule* FirstMatch(const SeriesFacts& facts) const;
  // Why no rule matched `facts`: for each rule in order, "rule 'NAME': " and
  // its first failing criterion (RuleMatch::FirstFailure), or that it is a
  // fill rule for a series / a job rule for a segmentation; "; " between
  // rules. One line, no UIDs or patient data.
  std::string ExplainNoMatch(const SeriesFacts& facts) const;
};

// `peers` are those of the peers file: send_to names must be among them.
absl::StatusOr<RuleSet> LoadRulesFile(const std::string& path,
                                      const std::vector<DicomPeer>& peers);

// An AE title as DICOM allows it (PS3.5 AE VR): 1-16 characters of the
// default repertoire without backslash or control characters, not all
// spaces. Returns it without surrounding spaces.
absl::StatusOr<std::string> NormalizeAeTitle(const std::string& text);

}  // namespace interslice::server::node

#endif  // INTERSLICE_SERVER_NODE_CONFIG_H_
