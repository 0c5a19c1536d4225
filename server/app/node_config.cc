#include "server/app/node_config.h"

#include <algorithm>
#include <cstdio>
#include <map>
#include <utility>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "core/dicom/series_reader.h"
#include "server/base/log_safe.h"
#include "server/net/dicomweb/dicomweb_peer.h"
#include "spdlog/spdlog.h"

namespace interslice::server {
namespace {

// "a series with modality CT, called_ae INTERSLICE -> job (complete on
// release), send_to orthanc"
std::string DescribeRule(const node::Rule& rule) {
  std::string text = absl::StrCat(
      rule.job.has_fill() ? "a segmentation (SEG, RTSTRUCT) with "
                          : "a series with ",
      rule.match.Describe(), " -> ", rule.job.has_fill() ? "fill job" : "job");
  if (rule.complete_on_release)
    absl::StrAppend(&text, " (complete on release)");
  if (!rule.send_to.empty()) {
    absl::StrAppend(&text, ", send_to ", absl::StrJoin(rule.send_to, ", "));
  }
  return text;
}

}  // namespace

// The peers file's content; none without --dicom-peers.
absl::StatusOr<node::PeersConfig> LoadPeers(const ServerOptions& options) {
  if (options.dicom_peers_file.empty()) return node::PeersConfig{};
  return node::LoadPeersConfig(options.dicom_peers_file);
}

absl::StatusOr<DicomConfig> LoadDicomConfig(const ServerOptions& options,
                                            node::PeersConfig peers) {
  DicomConfig config;
  config.peers = std::move(peers);
  if (!options.rules_file.empty()) {
    absl::StatusOr<node::RuleSet> loaded =
        node::LoadRulesFile(options.rules_file, config.peers.peers);
    if (!loaded.ok()) return loaded.status();
    config.rules = *std::move(loaded);
  } else {
    config.rules.path = "(none: --rules not given)";
  }
  config.ae_titles = options.dicom_ae_titles;
  if (config.ae_titles.empty()) config.ae_titles.push_back("INTERSLICE");
  for (std::string& ae : config.ae_titles) {
    absl::StatusOr<std::string> normal = node::NormalizeAeTitle(ae);
    if (!normal.ok()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "--dicom-ae '", LogSafe(ae), "': ", normal.status().message()));
    }
    ae = *normal;
  }
  const std::vector<std::string>& titles = config.ae_titles;
  for (size_t i = 0; i < config.rules.rules.size(); ++i) {
    const auto& called = config.rules.rules[i].match.called_ae;
    if (called &&
        std::find(titles.begin(), titles.end(), *called) == titles.end()) {
      return absl::InvalidArgumentError(absl::StrCat(
          options.rules_file, ": rule '", config.rules.rules[i].name, "' (#",
          i + 1, "): match.called_ae: ", *called,
          " is not an AE title this server listens as (--dicom-ae ",
          absl::StrJoin(titles, ", --dicom-ae "), ")"));
    }
  }
  return config;
}

absl::StatusOr<std::unique_ptr<node::SeriesAssembler>> StartDicomAssembler(
    const ServerOptions& options, node::RuleSet rules, Spool* spool,
    Metrics* metrics, JobManager* manager) {
  if (options.rules_file.empty()) {
    spdlog::warn("dicom: no --rules: received series make no jobs");
  }
  node::AssemblerOptions a;
  a.root = options.spool + "/dicom-in";
  a.max_instances_per_series = options.dicom_max_series_instances;
  a.max_bytes_per_series = options.dicom_max_series_bytes;
  a.unmatched_retention_seconds =
      static_cast<double>(options.retention_seconds);
  a.job_ended_without_results = [manager](const std::string& id) {
    std::shared_ptr<Job> job = manager->Find(id);
    if (job == nullptr) return false;
    const v1::JobState state = job->Snapshot(false).state();
    return state == v1::JOB_STATE_FAILED || state == v1::JOB_STATE_CANCELLED;
  };
  return node::SeriesAssembler::Open(
      a, std::move(rules), spool, metrics,
      [manager](const v1::JobSpec& spec, const std::string& dir,
                const std::string& origin,
                const std::string& segmentation_file) {
        // A fill rule's spec names the segmentation it takes (job/wire.h);
        // the node hands over the SEG or RTSTRUCT it received.
        std::map<std::string, std::string> named;
        if (!segmentation_file.empty()) {
          named[spec.fill().segmentation_file()] = segmentation_file;
        }
        return manager->SubmitLocalFiles(spec, dir, "dicom", origin, named);
      });
}

absl::StatusOr<std::unique_ptr<dimse::StorageScp>> StartDicomListener(
    const ServerOptions& options, node::PeersConfig peers,
    node::SeriesAssembler* assembler, Metrics* metrics, AuditLog* audit,
    dimse::PendingMoves* pending_moves) {
  dimse::StorageScpOptions o;
  o.audit = audit;
  o.pending_moves = pending_moves;
  const size_t colon = options.dicom_listen.rfind(':');
  int port = -1;
  if (colon == std::string::npos ||
      !absl::SimpleAtoi(options.dicom_listen.substr(colon + 1), &port) ||
      port < 0 || port > 65535) {
    return absl::InvalidArgumentError(
        absl::StrCat("--dicom-listen: expected HOST:PORT, got '",
                     LogSafe(options.dicom_listen), "'"));
  }
  o.host = options.dicom_listen.substr(0, colon);
  o.port = port;
  o.ae_titles = options.dicom_ae_titles;
  if (o.ae_titles.empty()) o.ae_titles = {"INTERSLICE"};
  for (std::string& ae : o.ae_titles) {
    ae = *node::NormalizeAeTitle(ae);  // checked by LoadDicomConfig
  }
  o.peers = std::move(peers);
  o.max_associations = options.dicom_max_associations;
  o.max_associations_per_source = options.dicom_max_associations_per_source;
  o.max_pending = options.dicom_max_pending;
  o.max_pending_per_source = options.dicom_max_pending_per_source;
  o.pdu_timeout_seconds = options.dicom_pdu_timeout_seconds;
  if (options.dicom_max_pdu < 4096 || options.dicom_max_pdu > 131072) {
    return absl::InvalidArgumentError(
        "--dicom-max-pdu must be between 4096 and 131072 bytes");
  }
  o.max_pdu_bytes = static_cast<uint32_t>(options.dicom_max_pdu);
  o.acse_timeout_seconds = options.dicom_acse_timeout_seconds;
  o.dimse_timeout_seconds = options.dicom_dimse_timeout_seconds;
  o.tls.certificate = options.dicom_tls_cert;
  o.tls.private_key = options.dicom_tls_key;
  o.tls.ca_certificates = options.dicom_tls_ca;
  return dimse::StorageScp::Start(o, assembler, metrics);
}

// A peer pulled from by C-MOVE sends to our listener: without one, no pull
// from it could ever succeed, so the start fails saying so.
absl::Status CheckMoveDestination(const std::string& dicom_listen,
                                  const std::vector<node::DicomPeer>& peers) {
  if (!dicom_listen.empty()) return absl::OkStatus();
  for (const node::DicomPeer& peer : peers) {
    if (peer.type == node::PeerType::kDimse &&
        peer.retrieve == node::RetrieveMethod::kMove) {
      return absl::InvalidArgumentError(absl::StrCat(
          "peer '", peer.name,
          "' has retrieve: move, which needs the DICOM listener "
          "(--dicom-listen): the server is its own C-MOVE destination"));
    }
  }
  return absl::OkStatus();
}

// Outgoing associations call as the first --dicom-ae (DeliveryOptions'
// default when none is given).
std::string CallingAeTitle(const ServerOptions& options) {
  if (options.dicom_ae_titles.empty()) return "INTERSLICE";
  absl::StatusOr<std::string> ae =
      node::NormalizeAeTitle(options.dicom_ae_titles.front());
  return ae.ok() ? *ae : options.dicom_ae_titles.front();
}

// How this server talks to its DICOM peers: as the first --dicom-ae, with
// the --dicom-tls-* files for DIMSE peers marked tls; the timeouts are the
// defaults of PeerClientSettings.
node::PeerClientSettings PeerSettings(const ServerOptions& options) {
  node::PeerClientSettings settings;
  settings.calling_ae_title = CallingAeTitle(options);
  settings.tls.certificate = options.dicom_tls_cert;
  settings.tls.private_key = options.dicom_tls_key;
  settings.tls.ca_certificates = options.dicom_tls_ca;
  return settings;
}

// The one place that chooses a peer's protocol by its type.
node::PeerClientFactory MakePeerClientFactory(node::PeerClientSettings settings,
                                              dimse::MoveDestination move) {
  return [settings = std::move(settings), move](
             const node::DicomPeer& peer) -> std::unique_ptr<node::PeerClient> {
    switch (peer.type) {
      case node::PeerType::kDicomWeb:
        return std::make_unique<dicomweb::DicomWebPeerClient>(peer, settings);
      case node::PeerType::kDimse:
        break;
    }
    return std::make_unique<dimse::DimsePeerClient>(peer, settings, move);
  };
}

// SIGHUP: the peers and rules files read again and checked exactly as at
// start-up; the peers (the listener's accepted callers, and the registry
// every delivery, pull and query asks for its peer) and the assembler's
// rules are replaced only when all of it is valid. A delivery's next try
// goes to its peer's reloaded address; jobs already made keep their spec.
absl::Status ReloadDicomConfig(const ServerOptions& options,
                               node::SeriesAssembler* assembler,
                               dimse::StorageScp* listener,
                               node::PeerRegistry* peers) {
  absl::StatusOr<node::PeersConfig> loaded = LoadPeers(options);
  if (!loaded.ok()) return loaded.status();
  absl::StatusOr<DicomConfig> config =
      LoadDicomConfig(options, *std::move(loaded));
  if (!config.ok()) return config.status();
  if (absl::Status s =
          CheckMoveDestination(options.dicom_listen, config->peers.peers);
      !s.ok()) {
    return s;
  }
  if (peers != nullptr) peers->SetPeers(config->peers);
  listener->SetPeers(std::move(config->peers));
  assembler->SetRules(std::move(config->rules));
  return absl::OkStatus();
}

int CheckConfig(const ServerOptions& options) {
  int problems = 0;
  auto problem = [&problems](const std::string& line) {
    ++problems;
    std::fprintf(stderr, "interslice-server: problem: %s\n", line.c_str());
  };
  QuietDicomToolkitLogging();
  absl::StatusOr<node::PeersConfig> loaded = LoadPeers(options);
  absl::StatusOr<DicomConfig> config =
      loaded.ok() ? LoadDicomConfig(options, *loaded)
                  : absl::StatusOr<DicomConfig>(loaded.status());
  std::vector<node::DicomPeer> peers;
  if (!config.ok()) {
    problem(std::string(config.status().message()));
    // The peers are still worth an echo when their own file is valid.
    if (loaded.ok()) peers = loaded->peers;
  } else {
    if (!options.dicom_peers_file.empty()) {
      std::printf("peers file %s: %zu peer(s)%s\n",
                  options.dicom_peers_file.c_str(), config->peers.peers.size(),
                  config->peers.accept_unknown_callers
                      ? ", unknown callers accepted"
                      : "");
    }
    peers.insert(peers.end(), config->peers.peers.begin(),
                 config->peers.peers.end());
    if (!options.dicom_listen.empty()) {
      std::printf("listening for DICOM on %s as %s\n",
                  options.dicom_listen.c_str(),
                  absl::StrJoin(config->ae_titles, ", ").c_str());
    }
    if (options.rules_file.empty()) {
      std::printf("no --rules: received series make no jobs\n");
    } else {
      std::printf(
          "rules file %s: %zu rule(s), stable_seconds %g; the first "
          "that matches wins\n",
          options.rules_file.c_str(), config->rules.rules.size(),
          config->rules.stable_seconds);
      for (size_t i = 0; i < config->rules.rules.size(); ++i) {
        const node::Rule& rule = config->rules.rules[i];
        std::printf("  rule '%s' (#%zu): %s\n", rule.name.c_str(), i + 1,
                    DescribeRule(rule).c_str());
      }
    }
  }
  // What the start would refuse (server.cc's Run), said here too.
  if (absl::Status s = CheckMoveDestination(options.dicom_listen, peers);
      !s.ok()) {
    problem(std::string(s.message()));
  }
  const node::PeerClientFactory make_client =
      MakePeerClientFactory(PeerSettings(options), {});
  for (const node::DicomPeer& peer : peers) {
    const std::unique_ptr<node::PeerClient> client = make_client(peer);
    if (absl::Status echo = client->Echo(); echo.ok()) {
      std::printf("  %s: %s\n", node::PeerLabel(peer).c_str(),
                  client->EchoAnswered().c_str());
    } else {
      problem(std::string(echo.message()));
    }
  }
  if (problems > 0) {
    std::fprintf(stderr, "interslice-server: --check-config: %d problem(s)\n",
                 problems);
    return 1;
  }
  std::printf("configuration OK\n");
  return 0;
}

}  // namespace interslice::server
