#include "server/node/config.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "job/options.h"
#include "job/wire.h"
#include "tests/testing/paths.h"

namespace interslice::server::node {
namespace {

namespace fs = std::filesystem;
using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::Not;

class ConfigTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("interslice-config-test-" + std::to_string(::getpid()) + "-" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }

  std::string Write(const std::string& name, const std::string& text) {
    const std::string path = (dir_ / name).string();
    std::ofstream(path) << text;
    return path;
  }

  std::vector<DicomPeer> Peers() {
    absl::StatusOr<std::vector<DicomPeer>> peers = LoadPeersFile(Write(
        "peers.yaml",
        "peers:\n"
        "  - {name: orthanc, ae_title: ORTHANC, host: 127.0.0.1, port: 4242}\n"
        "  - {name: ws, ae_title: WS, host: ws.example, tls: true}\n"));
    EXPECT_TRUE(peers.ok()) << peers.status();
    return peers.ok() ? *peers : std::vector<DicomPeer>{};
  }

  // The rules file made of `rule` (one list item) fails; returns the message.
  std::string RuleError(const std::string& rule) {
    const std::string path = Write("rules.yaml", "rules:\n" + rule);
    absl::StatusOr<RuleSet> set = LoadRulesFile(path, Peers());
    EXPECT_FALSE(set.ok()) << rule;
    if (set.ok()) return "";
    EXPECT_EQ(set.status().code(), absl::StatusCode::kInvalidArgument);
    const std::string message(set.status().message());
    // One line, naming the file.
    EXPECT_EQ(message.find('\n'), std::string::npos) << message;
    EXPECT_THAT(message, HasSubstr(path));
    return message;
  }

  std::string PeersError(const std::string& text) {
    const std::string path = Write("bad-peers.yaml", text);
    absl::StatusOr<PeersConfig> config = LoadPeersConfig(path);
    EXPECT_FALSE(config.ok()) << text;
    if (config.ok()) return "";
    EXPECT_EQ(config.status().code(), absl::StatusCode::kInvalidArgument);
    const std::string message(config.status().message());
    EXPECT_EQ(message.find('\n'), std::string::npos) << message;
    EXPECT_THAT(message, HasSubstr(path));
    return message;
  }

  fs::path dir_;
};

TEST_F(ConfigTest, PeersFileWithDefaults) {
  absl::StatusOr<PeersConfig> config = LoadPeersConfig(Write(
      "p.yaml",
      "accept_unknown_callers: true\n"
      "peers:\n"
      "  - {name: orthanc, ae_title: ' ORTHANC ', host: 127.0.0.1, port: "
      "4242, tls: false}\n"
      "  - name: ws\n    ae_title: WS\n    host: ws.example\n    tls: true\n"
      "    max_associations: 1\n"));
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_TRUE(config->accept_unknown_callers);
  ASSERT_EQ(config->peers.size(), 2u);
  EXPECT_EQ(config->peers[0].name, "orthanc");
  EXPECT_EQ(config->peers[0].ae_title, "ORTHANC");  // trimmed
  EXPECT_EQ(config->peers[0].port, 4242);
  EXPECT_FALSE(config->peers[0].tls);
  EXPECT_EQ(config->peers[1].port, 104);  // the DICOM default
  EXPECT_TRUE(config->peers[1].tls);
  EXPECT_EQ(config->peers[0].max_associations, 4);  // the default
  EXPECT_EQ(config->peers[1].max_associations, 1);
}

TEST_F(ConfigTest, MaxAssociationsIsBounded) {
  for (const char* bad : {"0", "17", "-1"}) {
    EXPECT_THAT(PeersError(absl::StrCat("peers:\n  - {name: a, ae_title: A, "
                                        "host: h, max_associations: ",
                                        bad, "}\n")),
                HasSubstr("peer 'a' (#1): max_associations: expected 1-16"))
        << bad;
  }
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: A, host: h, "
                         "max_associations: four}\n"),
              HasSubstr("max_associations: expected an integer"));
}

TEST_F(ConfigTest, RetrieveIsGetOrMove) {
  absl::StatusOr<PeersConfig> config = LoadPeersConfig(
      Write("p.yaml",
            "peers:\n"
            "  - {name: a, ae_title: A, host: h}\n"
            "  - {name: b, ae_title: B, host: h, retrieve: move}\n"
            "  - {name: c, ae_title: C, host: h, retrieve: ' GET '}\n"));
  ASSERT_TRUE(config.ok()) << config.status();
  ASSERT_EQ(config->peers.size(), 3u);
  EXPECT_EQ(config->peers[0].retrieve, RetrieveMethod::kGet);  // the default
  EXPECT_EQ(config->peers[1].retrieve, RetrieveMethod::kMove);
  EXPECT_EQ(config->peers[2].retrieve, RetrieveMethod::kGet);
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: A, host: h, "
                         "retrieve: find}\n"),
              HasSubstr("peer 'a' (#1): retrieve: 'find': expected get"));
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: A, host: h, "
                         "retrieve: [move]}\n"),
              HasSubstr("retrieve: expected text"));
  // DIMSE only: a DICOMweb peer pulls by QIDO-RS + WADO-RS.
  EXPECT_THAT(PeersError("peers:\n  - {name: w, type: dicomweb, url: "
                         "'http://h/dicom-web', retrieve: move}\n"),
              HasSubstr("peer 'w' (#1): retrieve: not for a DICOMweb peer"));
}

TEST_F(ConfigTest, PeersFileAsJson) {
  absl::StatusOr<PeersConfig> config = LoadPeersConfig(
      Write("p.json",
            R"({"peers": [{"name": "orthanc", "ae_title": "ORTHANC",
          "host": "127.0.0.1", "port": 4242, "tls": false}]})"));
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_FALSE(config->accept_unknown_callers);
  ASSERT_EQ(config->peers.size(), 1u);
  EXPECT_EQ(config->peers[0].port, 4242);
}

TEST_F(ConfigTest, PeersFileErrorsNameThePeerAndField) {
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: A, host: h, "
                         "prot: 1}\n"),
              HasSubstr("peer 'a' (#1): prot: unknown key"));
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: A, host: h, "
                         "port: '4242'}\n"),
              HasSubstr("peer 'a' (#1): port: expected an integer"));
  EXPECT_THAT(PeersError(R"({"peers": [{"name": "a", "ae_title": "A",
                            "host": "h", "port": "4242"}]})"),
              HasSubstr("port: expected an integer"));
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: A, host: h, "
                         "port: 70000}\n"),
              HasSubstr("port: expected a port number"));
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: A, host: h, "
                         "tls: maybe}\n"),
              HasSubstr("tls: expected true or false"));
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: "
                         "THIS_IS_SEVENTEEN, host: h}\n"),
              HasSubstr("ae_title: an AE title has 1 to 16"));
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: 'A\\B', host: h}\n"),
              HasSubstr("ae_title: an AE title holds no backslash"));
  EXPECT_THAT(PeersError("peers:\n  - {name: a, host: h}\n"),
              HasSubstr("peer 'a' (#1): ae_title: missing"));
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: A, host: h}\n"
                         "  - {name: a, ae_title: B, host: h}\n"),
              HasSubstr("peer 'a' (#2): name: another peer has this name"));
  EXPECT_THAT(PeersError("peers: {name: a}\n"),
              HasSubstr("peers: expected a list"));
  EXPECT_THAT(PeersError("peers: []\nallow_all: true\n"),
              HasSubstr("allow_all: unknown key"));
  EXPECT_THAT(PeersError("peers: [\n"), HasSubstr("not valid YAML or JSON"));
  EXPECT_THAT(
      LoadPeersConfig((dir_ / "missing.yaml").string()).status().message(),
      HasSubstr("cannot read"));
}

// Issue 22: a peer may be bound to addresses (allowed_sources).
TEST_F(ConfigTest, PeerAllowedSources) {
  absl::StatusOr<PeersConfig> config = LoadPeersConfig(
      Write("p.yaml",
            "peers:\n"
            "  - {name: ct, ae_title: CT1, host: 10.1.2.3,\n"
            "     allowed_sources: [10.1.0.0/16, 192.168.7.9, 'fd00::/8']}\n"
            "  - {name: any, ae_title: ANY, host: h}\n"));
  ASSERT_TRUE(config.ok()) << config.status();
  const std::vector<SourceNetwork>& nets = config->peers[0].allowed_sources;
  ASSERT_EQ(nets.size(), 3u);
  EXPECT_TRUE(config->peers[1].allowed_sources.empty());
  EXPECT_TRUE(InNetwork("10.1.200.7", nets[0]));
  EXPECT_FALSE(InNetwork("10.2.0.1", nets[0]));
  EXPECT_TRUE(InNetwork("192.168.7.9", nets[1]));
  EXPECT_FALSE(InNetwork("192.168.7.10", nets[1]));
  EXPECT_TRUE(InNetwork("fd12:3456::1", nets[2]));
  EXPECT_FALSE(InNetwork("fe80::1", nets[2]));
  EXPECT_FALSE(InNetwork("10.1.2.3", nets[2]));  // another family
  // Prefixes that end inside a byte.
  absl::StatusOr<SourceNetwork> odd = ParseSourceNetwork("172.16.0.0/12");
  ASSERT_TRUE(odd.ok());
  EXPECT_TRUE(InNetwork("172.31.255.255", *odd));
  EXPECT_FALSE(InNetwork("172.32.0.0", *odd));
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: A, host: h, "
                         "allowed_sources: [pacs.example]}\n"),
              HasSubstr("peer 'a' (#1): allowed_sources[0]: 'pacs.example' "
                        "is not an IPv4 or IPv6 address"));
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: A, host: h, "
                         "allowed_sources: [10.0.0.0/33]}\n"),
              HasSubstr("an IPv4 prefix is at most 32 bits"));
  EXPECT_THAT(PeersError("peers:\n  - {name: a, ae_title: A, host: h, "
                         "allowed_sources: []}\n"),
              HasSubstr("allowed_sources: expected a non-empty list"));
}

// Issue 27: DICOMweb peers (type: dicomweb) with their URL and credentials.
TEST_F(ConfigTest, DicomWebPeers) {
  const std::string token = Write("token", "s3cret-token\n");
  const std::string password = Write("pw", "hunter2\n");
  const std::string cert = Write("c.pem", "-----BEGIN CERTIFICATE-----\n");
  const std::string key = Write("k.pem", "-----BEGIN PRIVATE KEY-----\n");
  absl::StatusOr<PeersConfig> config = LoadPeersConfig(Write(
      "p.yaml",
      absl::StrCat(
          "peers:\n"
          "  - {name: pacs, ae_title: PACS, host: h}\n"
          "  - {name: web, type: dicomweb, url: 'http://127.0.0.1:8042/"
          "dicom-web/', bearer_token_file: ",
          token,
          ", max_associations: 2}\n"
          "  - {name: basic, type: DICOMweb, url: 'https://pacs.example/dw',\n"
          "     basic_user: interslice, basic_password_file: ",
          password, ",\n     client_certificate: ", cert, ", client_key: ", key,
          ", ca_certificates: ", cert, "}\n")));
  ASSERT_TRUE(config.ok()) << config.status();
  ASSERT_EQ(config->peers.size(), 3u);
  EXPECT_EQ(config->peers[0].type, PeerType::kDimse);
  const DicomPeer& web = config->peers[1];
  EXPECT_EQ(web.type, PeerType::kDicomWeb);
  EXPECT_EQ(web.web.url, "http://127.0.0.1:8042/dicom-web");  // no final /
  EXPECT_EQ(web.web.bearer_token_file, token);
  EXPECT_EQ(web.max_associations, 2);
  EXPECT_TRUE(web.ae_title.empty());
  const DicomPeer& basic = config->peers[2];
  EXPECT_EQ(basic.type, PeerType::kDicomWeb);
  EXPECT_EQ(basic.web.basic_user, "interslice");
  EXPECT_EQ(basic.web.basic_password_file, password);
  EXPECT_EQ(basic.web.client_certificate, cert);
  EXPECT_EQ(basic.web.client_key, key);
  EXPECT_EQ(basic.web.ca_certificates, cert);
}

TEST_F(ConfigTest, DicomWebPeerErrorsNameThePeerAndKey) {
  const std::string token = Write("token", "s3cret-token\n");
  const std::string empty = Write("empty", "  \n");
  const std::string head = "peers:\n  - {name: w, type: dicomweb, ";
  EXPECT_THAT(PeersError(head + "}\n"), HasSubstr("peer 'w' (#1): url: "
                                                  "missing"));
  EXPECT_THAT(PeersError(head + "url: 'http://h/dw', ae_title: W}\n"),
              HasSubstr("peer 'w' (#1): ae_title: not for a DICOMweb peer"));
  EXPECT_THAT(PeersError(head + "url: 'http://h/dw', port: 80}\n"),
              HasSubstr("port: not for a DICOMweb peer"));
  EXPECT_THAT(PeersError(head + "url: 'http://h/dw', tls: true}\n"),
              HasSubstr("tls: not for a DICOMweb peer"));
  EXPECT_THAT(PeersError("peers:\n  - {name: d, ae_title: D, host: h, "
                         "url: 'http://h/dw'}\n"),
              HasSubstr("peer 'd' (#1): url: only for a DICOMweb peer"));
  EXPECT_THAT(PeersError("peers:\n  - {name: d, type: dicom, ae_title: D, "
                         "host: h}\n"),
              HasSubstr("type: 'dicom': expected dimse"));
  EXPECT_THAT(PeersError(head + "url: 'ftp://h/dw'}\n"),
              HasSubstr("url: expected an http:// or https:// URL"));
  EXPECT_THAT(PeersError(head + "url: 'http:///dw'}\n"),
              HasSubstr("url: has no host"));
  EXPECT_THAT(PeersError(head + "url: 'http://h/dw?x=1'}\n"),
              HasSubstr("url: expected a base URL without query"));
  // Credentials in the URL would be shown wherever the URL is.
  const std::string with_user =
      PeersError(head + "url: 'http://me:pw@h/dw'}\n");
  EXPECT_THAT(with_user, HasSubstr("url: has credentials in it"));
  EXPECT_THAT(with_user, Not(HasSubstr("me:pw")));
  EXPECT_THAT(PeersError(head + "url: 'http://h/dw', bearer_token_file: " +
                         (dir_ / "nope").string() + "}\n"),
              HasSubstr("bearer_token_file: '" + (dir_ / "nope").string() +
                        "' is not a file"));
  EXPECT_THAT(PeersError(head + "url: 'http://h/dw', bearer_token_file: " +
                         empty + "}\n"),
              HasSubstr("bearer_token_file: '" + empty + "' is empty"));
  EXPECT_THAT(PeersError(head + "url: 'http://h/dw', basic_user: u}\n"),
              HasSubstr("basic_password_file: missing"));
  EXPECT_THAT(PeersError(head + "url: 'http://h/dw', basic_password_file: " +
                         token + "}\n"),
              HasSubstr("basic_user: missing"));
  EXPECT_THAT(PeersError(head +
                         "url: 'http://h/dw', basic_user: 'a:b', "
                         "basic_password_file: " +
                         token + "}\n"),
              HasSubstr("basic_user: has a ':'"));
  EXPECT_THAT(PeersError(head +
                         "url: 'http://h/dw', basic_user: u, "
                         "basic_password_file: " +
                         token + ", bearer_token_file: " + token + "}\n"),
              HasSubstr("bearer_token_file: give either"));
  EXPECT_THAT(PeersError(head + "url: 'https://h/dw', client_certificate: " +
                         token + "}\n"),
              HasSubstr("client_key: missing"));
  EXPECT_THAT(PeersError(head + "url: 'http://h/dw', ca_certificates: " +
                         token + "}\n"),
              HasSubstr("ca_certificates: only for an https:// url"));
  // The secret's contents never appear in a message.
  EXPECT_THAT(PeersError(head + "url: 'http://h/dw', bearer_token_file: " +
                         token + ", host: x}\n"),
              Not(HasSubstr("s3cret")));
  if (::geteuid() != 0) {  // root reads any file
    const std::string locked = Write("locked", "x\n");
    fs::permissions(locked, fs::perms::none);
    EXPECT_THAT(PeersError(head + "url: 'http://h/dw', bearer_token_file: " +
                           locked + "}\n"),
                HasSubstr("cannot read"));
  }
}

TEST_F(ConfigTest, FullRulesFile) {
  absl::StatusOr<RuleSet> set = LoadRulesFile(
      Write("rules.yaml",
            "stable_seconds: 1.5\n"
            "rules:\n"
            "  - name: ct-bone\n"
            "    match: {modality: CT, series_description: '(?i)head',\n"
            "            protocol_name: 'bone|skull', body_part: HEAD,\n"
            "            slice_thickness: {min: 2, max: 6},\n"
            "            slice_spacing: [2, 6], slice_count: {min: 10},\n"
            "            calling_ae: ORTHANC, called_ae: INTERSLICE}\n"
            "    job: {threshold: 300, upper: 2000, method: direct,\n"
            "          spacing: 1.25, roi: [1, 2, 3, 40, 50, 60],\n"
            "          output_series: [intensity, mask], seg: true,\n"
            "          mesh: [stl, ply], volume: none, uid_root: '1.2.3',\n"
            "          energy_units: mm}\n"
            "    send_to: [orthanc, ws]\n"
            "    complete_on_release: true\n"
            "    complete_on_request: true\n"
            "  - match: {modality: MR}\n"
            "    job: {threshold: 100, method: cg, iterations: 20,\n"
            "          tolerance: 0.001, factor: 3, mesh: 'stl,obj',\n"
            "          roi_mm: [-80.5, 20, -3e1, 60, -40.25, 10]}\n"),
      Peers());
  ASSERT_TRUE(set.ok()) << set.status();
  EXPECT_DOUBLE_EQ(set->stable_seconds, 1.5);
  ASSERT_EQ(set->rules.size(), 2u);
  const Rule& bone = set->rules[0];
  EXPECT_EQ(bone.name, "ct-bone");
  EXPECT_TRUE(bone.complete_on_release);
  EXPECT_TRUE(bone.complete_on_request);
  EXPECT_THAT(bone.send_to, ElementsAre("orthanc", "ws"));
  const v1::JobSpec& job = bone.job;
  EXPECT_FLOAT_EQ(job.threshold(), 300);
  EXPECT_FLOAT_EQ(job.upper_threshold(), 2000);
  EXPECT_EQ(job.method(), v1::SOLVER_METHOD_DIRECT);
  EXPECT_DOUBLE_EQ(job.slice_spacing_mm(), 1.25);
  EXPECT_EQ(job.roi().x0(), 1);
  EXPECT_EQ(job.roi().z1(), 60);
  EXPECT_THAT(job.derived_series().contents(),
              ElementsAre("intensity", "mask"));
  EXPECT_TRUE(job.segmentation().enabled());
  EXPECT_THAT(job.outputs().mesh_formats(),
              ElementsAre(v1::MESH_FORMAT_STL, v1::MESH_FORMAT_PLY));
  EXPECT_EQ(job.outputs().volume_formats_size(), 0);
  EXPECT_EQ(job.uid_root(), "1.2.3");
  EXPECT_EQ(job.energy_units(), v1::ENERGY_UNITS_MILLIMETRE);
  EXPECT_THAT(job.send_to(), ElementsAre("orthanc", "ws"));

  const Rule& mr = set->rules[1];
  EXPECT_EQ(mr.name, "#2");
  EXPECT_FALSE(mr.complete_on_release);
  EXPECT_FALSE(mr.complete_on_request);
  EXPECT_EQ(mr.job.method(), v1::SOLVER_METHOD_CONJUGATE_GRADIENT);
  EXPECT_EQ(mr.job.max_iterations(), 20);
  EXPECT_DOUBLE_EQ(mr.job.tolerance(), 0.001);
  EXPECT_EQ(mr.job.insertion_factor(), 3);
  // roi_mm as a YAML list of numbers (corners in any order), and as text.
  EXPECT_FALSE(job.has_roi_mm());
  ASSERT_TRUE(mr.job.has_roi_mm());
  EXPECT_DOUBLE_EQ(mr.job.roi_mm().x0(), -80.5);
  EXPECT_DOUBLE_EQ(mr.job.roi_mm().x1(), 60);
  EXPECT_DOUBLE_EQ(mr.job.roi_mm().y0(), -40.25);
  EXPECT_DOUBLE_EQ(mr.job.roi_mm().z0(), -30);
  EXPECT_DOUBLE_EQ(mr.job.roi_mm().z1(), 10);
  EXPECT_THAT(mr.job.outputs().mesh_formats(),
              ElementsAre(v1::MESH_FORMAT_STL, v1::MESH_FORMAT_OBJ));
  // The command line's default: NIfTI unless `volume` says otherwise.
  EXPECT_THAT(mr.job.outputs().volume_formats(),
              ElementsAre(v1::VOLUME_FORMAT_NIFTI));

  SeriesFacts facts;
  facts.modality = "CT";
  facts.series_description = "Routine HEAD 5mm";
  facts.protocol_name = "skull base";
  facts.body_part = "head";
  facts.slice_thickness_mm = 5;
  facts.slice_spacing_mm = 5;
  facts.slice_count = 28;
  facts.calling_ae = "ORTHANC";
  facts.called_ae = "INTERSLICE";
  EXPECT_EQ(set->FirstMatch(facts), &set->rules[0]);
  SeriesFacts other = facts;
  other.called_ae = "OTHER";
  EXPECT_EQ(set->FirstMatch(other), nullptr);
  other = facts;
  other.series_description = "chest";
  EXPECT_EQ(set->FirstMatch(other), nullptr);
  other = facts;
  other.slice_thickness_mm.reset();  // unknown: a range does not hold
  EXPECT_EQ(set->FirstMatch(other), nullptr);
  other = facts;
  other.slice_thickness_mm = 7;
  EXPECT_EQ(set->FirstMatch(other), nullptr);
  other = facts;
  other.slice_count = 9;
  EXPECT_EQ(set->FirstMatch(other), nullptr);
  other = facts;
  other.modality = "mr";  // falls through to the MR rule
  EXPECT_EQ(set->FirstMatch(other), &set->rules[1]);
}

// The rule key `dicom_layout` (job/options.cc) reaches the rule's wire spec,
// which the server turns back into the JobSpec its pipeline writes from.
TEST_F(ConfigTest, RuleDicomLayoutReachesTheJobSpec) {
  absl::StatusOr<RuleSet> set = LoadRulesFile(
      Write("rules.yaml",
            "rules:\n"
            "  - name: enhanced\n"
            "    job: {threshold: 300, output_series: [intensity, mask],\n"
            "          dicom_layout: enhanced}\n"
            "  - name: default\n"
            "    job: {threshold: 300}\n"),
      Peers());
  ASSERT_TRUE(set.ok()) << set.status();
  ASSERT_EQ(set->rules.size(), 2u);
  EXPECT_EQ(set->rules[0].job.derived_series().layout(),
            v1::DICOM_LAYOUT_ENHANCED);
  absl::StatusOr<interslice::JobSpec> spec =
      job::JobSpecFromWire(set->rules[0].job);
  ASSERT_TRUE(spec.ok()) << spec.status();
  EXPECT_EQ(spec->dicom_layout, "enhanced");
  EXPECT_EQ(set->rules[1].job.derived_series().layout(),
            v1::DICOM_LAYOUT_UNSPECIFIED);
  EXPECT_EQ(job::JobSpecFromWire(set->rules[1].job)->dicom_layout, "classic");
  EXPECT_THAT(
      RuleError("  - {name: a, job: {threshold: 1, dicom_layout: tiled}}\n"),
      HasSubstr("dicom_layout"));
}

// Regression (issue 25): a rule for a modality without an enhanced IOD
// (written here: CT and MR) loaded, and every series it matched made a job
// that failed FAILED_PRECONDITION. It is refused when the file is loaded (at
// start, --check-config, SIGHUP).
TEST_F(ConfigTest, EnhancedLayoutOnANonCtOrMrRuleIsRefusedAtLoad) {
  const std::string error = RuleError(
      "  - {name: pet, match: {modality: PT},\n"
      "     job: {threshold: 100, output_series: [intensity],\n"
      "           dicom_layout: enhanced}}\n");
  EXPECT_THAT(error, HasSubstr("rule 'pet'"));
  EXPECT_THAT(error,
              HasSubstr("dicom_layout enhanced is written for CT and MR only"));
  EXPECT_THAT(error, HasSubstr("'PT'"));
  // MR (Enhanced MR Image) loads.
  absl::StatusOr<RuleSet> mr = LoadRulesFile(
      Write("rules-mr.yaml",
            "rules:\n"
            "  - {name: mr, match: {modality: MR},\n"
            "     job: {threshold: 100, output_series: [intensity],\n"
            "           dicom_layout: enhanced}}\n"),
      Peers());
  ASSERT_TRUE(mr.ok()) << mr.status();
  EXPECT_EQ(mr->rules[0].job.derived_series().layout(),
            v1::DICOM_LAYOUT_ENHANCED);
  // CT (any case) and rules without a modality criterion still load.
  absl::StatusOr<RuleSet> set = LoadRulesFile(
      Write("rules-ct.yaml",
            "rules:\n"
            "  - {name: ct, match: {modality: ct},\n"
            "     job: {threshold: 300, dicom_layout: enhanced}}\n"
            "  - {name: any, job: {threshold: 300, dicom_layout: enhanced}}\n"),
      Peers());
  ASSERT_TRUE(set.ok()) << set.status();
  EXPECT_EQ(set->rules.size(), 2u);
}

TEST_F(ConfigTest, RulesFileAsJson) {
  absl::StatusOr<RuleSet> set =
      LoadRulesFile(Write("rules.json",
                          R"({"stable_seconds": 2, "rules": [{"name": "all",
                "job": {"threshold": 300, "mesh": ["stl"], "seg": true},
                "send_to": ["orthanc"], "complete_on_release": false}]})"),
                    Peers());
  ASSERT_TRUE(set.ok()) << set.status();
  EXPECT_DOUBLE_EQ(set->stable_seconds, 2);
  ASSERT_EQ(set->rules.size(), 1u);
  EXPECT_TRUE(set->rules[0].job.segmentation().enabled());
  // No criteria: every series.
  EXPECT_EQ(set->FirstMatch(SeriesFacts{}), &set->rules[0]);
}

TEST_F(ConfigTest, StableSecondsDefault) {
  absl::StatusOr<RuleSet> set = LoadRulesFile(
      Write("r.yaml", "rules:\n  - job: {threshold: 1}\n"), Peers());
  ASSERT_TRUE(set.ok()) << set.status();
  EXPECT_DOUBLE_EQ(set->stable_seconds, 30);
}

TEST_F(ConfigTest, UnknownKeys) {
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1}, sendto: [x]}\n"),
              HasSubstr("rule 'a' (#1): sendto: unknown key"));
  EXPECT_THAT(RuleError("  - {name: a, match: {modality: CT, series: x}, "
                        "job: {threshold: 1}}\n"),
              HasSubstr("rule 'a' (#1): match.series: unknown key"));
  EXPECT_THAT(RuleError("  - {job: {threshold: 1, thresh: 2}}\n"),
              HasSubstr("rule #1: job.thresh: unknown key"));
  const std::string path = Write("top.yaml", "stable: 3\nrules: []\n");
  EXPECT_THAT(LoadRulesFile(path, Peers()).status().message(),
              HasSubstr("stable: unknown key"));
}

TEST_F(ConfigTest, WrongTypes) {
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: '300'}}\n"),
              HasSubstr("rule 'a' (#1): job.threshold: expected a number"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: high}}\n"),
              HasSubstr("job.threshold: expected a number, got 'high'"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1, seg: yes}}\n"),
              HasSubstr("job.seg: expected true or false"));
  EXPECT_THAT(
      RuleError("  - {name: a, job: {threshold: 1, iterations: 1.5}}\n"),
      HasSubstr("job.iterations: expected an integer"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1, mesh: {a: b}}}\n"),
              HasSubstr("job.mesh: expected a list"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1, roi: [1, 2, x]}}\n"),
              HasSubstr("job.roi[2]: expected an integer"));
  EXPECT_THAT(RuleError("  - {name: a, match: [CT], job: {threshold: 1}}\n"),
              HasSubstr("rule 'a' (#1): match: expected a mapping"));
  EXPECT_THAT(RuleError("  - {name: a, match: {slice_count: 5}, "
                        "job: {threshold: 1}}\n"),
              HasSubstr("match.slice_count: expected {min: A, max: B}"));
  EXPECT_THAT(RuleError("  - {name: a, match: {slice_count: {min: 5, max: 2}}, "
                        "job: {threshold: 1}}\n"),
              HasSubstr("match.slice_count: min is greater than max"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1}, "
                        "complete_on_release: 1}\n"),
              HasSubstr("complete_on_release: expected true or false"));
  EXPECT_THAT(RuleError("  - just text\n"),
              HasSubstr("rule #1: expected a mapping"));
}

TEST_F(ConfigTest, BadRegularExpression) {
  EXPECT_THAT(RuleError("  - name: a\n    match: {series_description: "
                        "'(?i(head'}\n    job: {threshold: 1}\n"),
              HasSubstr("rule 'a' (#1): match.series_description: bad "
                        "regular expression"));
  EXPECT_THAT(RuleError("  - name: b\n    match: {protocol_name: '[a-'}\n"
                        "    job: {threshold: 1}\n"),
              HasSubstr("rule 'b' (#1): match.protocol_name: bad regular"));
}

TEST_F(ConfigTest, UnknownPeer) {
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1}, "
                        "send_to: [orthanc, pacs2]}\n"),
              HasSubstr("rule 'a' (#1): send_to: unknown peer 'pacs2'"));
}

// Every option of the job layer is a rule key: the intensity series'
// method among them.
TEST_F(ConfigTest, IntensityMethodIsARuleKey) {
  absl::StatusOr<RuleSet> set = LoadRulesFile(
      Write("rules.yaml",
            "rules:\n"
            "  - {name: a, job: {threshold: 300, output_series: [intensity], "
            "intensity_method: linear}}\n"
            "  - {name: b, job: {threshold: 300, output_series: [intensity]}}\n"
            "  - {name: c, fill: {factor: 2, intensity_method: linear}}\n"),
      Peers());
  ASSERT_TRUE(set.ok()) << set.status();
  EXPECT_EQ(set->rules[0].job.derived_series().intensity_method(),
            v1::INTENSITY_INTERPOLATION_LINEAR);
  EXPECT_EQ(set->rules[1].job.derived_series().intensity_method(),
            v1::INTENSITY_INTERPOLATION_MORPH);
  EXPECT_EQ(set->rules[2].job.fill().intensity_method(),
            v1::INTENSITY_INTERPOLATION_LINEAR);
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1, intensity_method: "
                        "cubic}}\n"),
              HasSubstr("job.intensity_method: unknown value 'cubic'"));
}

TEST_F(ConfigTest, JobValuesCheckedAsTheCommandLineChecksThem) {
  EXPECT_THAT(RuleError("  - {name: a, job: {upper: 5}}\n"),
              HasSubstr("rule 'a' (#1): job.threshold: missing"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1, method: fast}}\n"),
              HasSubstr("rule 'a' (#1): job.method: unknown method 'fast'"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1, energy_units: "
                        "inch}}\n"),
              HasSubstr("job.energy_units: unknown units 'inch'"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1, mesh: [stl, "
                        "vrml]}}\n"),
              HasSubstr("job.mesh: unknown value 'vrml'"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1, factor: 2, "
                        "spacing: 1}}\n"),
              HasSubstr("job.factor: factor and spacing are alternatives"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1, roi: [1, 2, 3]}}\n"),
              HasSubstr("job.roi: expected six integers"));
  EXPECT_THAT(
      RuleError("  - {name: a, job: {threshold: 1, roi_mm: [1, 2, x]}}\n"),
      HasSubstr("job.roi_mm[2]"));
  EXPECT_THAT(
      RuleError("  - {name: a, job: {threshold: 1, roi_mm: '1,2,3'}}\n"),
      HasSubstr("job.roi_mm: expected six numbers"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1, roi: [0, 0, 0, 9, "
                        "9, 2], roi_mm: [0, 0, 0, 9, 9, 9]}}\n"),
              HasSubstr("job.roi_mm: cannot be combined with roi"));
  EXPECT_THAT(RuleError("  - {name: a}\n"),
              HasSubstr("rule 'a' (#1): job: missing"));
}

TEST_F(ConfigTest, OtherRuleErrors) {
  EXPECT_THAT(RuleError("  - {name: a, match: {called_ae: ''}, "
                        "job: {threshold: 1}}\n"),
              HasSubstr("rule 'a' (#1): match.called_ae: an AE title"));
  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1}}\n"
                        "  - {name: a, job: {threshold: 2}}\n"),
              HasSubstr("rule 'a' (#2): name: another rule has this name"));
  EXPECT_THAT(
      LoadRulesFile(Write("s.yaml", "stable_seconds: 0\nrules: []\n"), Peers())
          .status()
          .message(),
      HasSubstr("stable_seconds: expected a number of seconds > 0"));
  EXPECT_THAT(LoadRulesFile(Write("n.yaml", "stable_seconds: 3\n"), Peers())
                  .status()
                  .message(),
              HasSubstr("rules: missing"));
}

// Fill rules: the `interslice fill` options, checked as the
// server checks an uploaded fill spec; they match segmentations only, and
// job rules never match a segmentation.
TEST_F(ConfigTest, FillRules) {
  absl::StatusOr<RuleSet> set = LoadRulesFile(
      Write("fill.yaml",
            "rules:\n"
            "  - name: everything\n"
            "    job: {threshold: 300}\n"
            "  - name: seg\n"
            "    match: {modality: SEG}\n"
            "    fill: {labels: [1, 3], key_slices: [0, 5, 10], method: "
            "direct, factor: 2, mesh: [ply], volume: [nii, nrrd], seg: "
            "false, rtstruct: true}\n"
            "    send_to: [orthanc]\n"
            "  - name: any-segmentation\n"
            "    fill:\n"),
      Peers());
  ASSERT_TRUE(set.ok()) << set.status();
  ASSERT_EQ(set->rules.size(), 3u);
  const v1::JobSpec& fill = set->rules[1].job;
  ASSERT_TRUE(fill.has_fill());
  EXPECT_THAT(fill.fill().labels(), ::testing::ElementsAre(1, 3));
  EXPECT_THAT(fill.fill().key_slices(), ::testing::ElementsAre(0, 5, 10));
  EXPECT_EQ(fill.method(), v1::SOLVER_METHOD_DIRECT);
  EXPECT_EQ(fill.insertion_factor(), 2);
  EXPECT_THAT(fill.outputs().mesh_formats(),
              ::testing::ElementsAre(v1::MESH_FORMAT_PLY));
  EXPECT_EQ(fill.outputs().volume_formats_size(), 2);
  EXPECT_THAT(fill.send_to(), ::testing::ElementsAre("orthanc"));
  EXPECT_FALSE(fill.has_threshold());
  EXPECT_FALSE(fill.fill().seg());
  ASSERT_TRUE(fill.fill().has_rtstruct());
  EXPECT_TRUE(fill.fill().rtstruct());
  // Defaults as `interslice fill` (NIfTI labels, STL meshes, the auto
  // method), and a SEG back for what came in as DICOM.
  const v1::JobSpec& plain = set->rules[2].job;
  ASSERT_TRUE(plain.has_fill());
  EXPECT_TRUE(plain.fill().seg());
  EXPECT_FALSE(plain.fill().has_rtstruct());
  EXPECT_EQ(plain.method(), v1::SOLVER_METHOD_UNSPECIFIED);
  absl::StatusOr<FillJobSpec> wire = job::FillJobSpecFromWire(plain);
  ASSERT_TRUE(wire.ok()) << wire.status();
  EXPECT_EQ(wire->fill.method, FillMethod::kAuto);
  EXPECT_TRUE(wire->write_seg);
  EXPECT_FALSE(wire->write_rtstruct.has_value());
  absl::StatusOr<FillJobSpec> direct = job::FillJobSpecFromWire(fill);
  ASSERT_TRUE(direct.ok()) << direct.status();
  EXPECT_EQ(direct->fill.method, FillMethod::kSolver);
  EXPECT_EQ(direct->fill.solver.method, SolverMethod::kDirect);
  EXPECT_EQ(direct->write_rtstruct, std::optional<bool>(true));
  EXPECT_THAT(plain.outputs().volume_formats(),
              ::testing::ElementsAre(v1::VOLUME_FORMAT_NIFTI));
  EXPECT_THAT(plain.outputs().mesh_formats(),
              ::testing::ElementsAre(v1::MESH_FORMAT_STL));

  SeriesFacts ct;
  ct.modality = "CT";
  SeriesFacts seg;
  seg.modality = "SEG";
  seg.segmentation = true;
  SeriesFacts rtstruct;
  rtstruct.modality = "RTSTRUCT";
  rtstruct.segmentation = true;
  ASSERT_NE(set->FirstMatch(ct), nullptr);
  EXPECT_EQ(set->FirstMatch(ct)->name, "everything");
  ASSERT_NE(set->FirstMatch(seg), nullptr);
  EXPECT_EQ(set->FirstMatch(seg)->name, "seg");
  ASSERT_NE(set->FirstMatch(rtstruct), nullptr);
  EXPECT_EQ(set->FirstMatch(rtstruct)->name, "any-segmentation");

  EXPECT_THAT(RuleError("  - {name: a, job: {threshold: 1}, fill: {}}\n"),
              HasSubstr("rule 'a' (#1): fill: a rule has either a job"));
  EXPECT_THAT(RuleError("  - {name: a, fill: {labels: [0]}}\n"),
              HasSubstr("fill.labels: 0 is not a label (1..65535)"));
  EXPECT_THAT(RuleError("  - {name: a, fill: {key_slices: [1, 1]}}\n"),
              HasSubstr("fill.key_slices: slice 1 is repeated"));
  EXPECT_THAT(RuleError("  - {name: a, fill: {method: fast}}\n"),
              HasSubstr("fill.method: unknown method 'fast'"));
  EXPECT_THAT(RuleError("  - {name: a, fill: {threshold: 3}}\n"),
              HasSubstr("fill.threshold: unknown key"));
  // A received SEG or RTSTRUCT names its segments itself: the command
  // line's and the wire's label names are no rules-file key.
  EXPECT_THAT(RuleError("  - {name: a, fill: {label_names: names.csv}}\n"),
              HasSubstr("fill.label_names: unknown key"));
  EXPECT_THAT(RuleError("  - {name: a, fill: {mesh: [vrml]}}\n"),
              HasSubstr("fill.mesh: unknown value 'vrml'"));
  EXPECT_THAT(RuleError("  - {name: a, fill: {labels: 3}}\n"),
              HasSubstr("fill.labels: expected a list of integers"));
}

// docs/dicom-node.md lists every key a rule's `job:` and `fill:` take (the
// option tables of job/options.h), so that the documentation cannot drift
// from what the parser accepts.
TEST_F(ConfigTest, DocumentationListsEveryRuleKey) {
  std::ifstream in(std::string(::interslice::testing::SourceDir()) +
                   "/docs/dicom-node.md");
  const std::string doc((std::istreambuf_iterator<char>(in)), {});
  ASSERT_FALSE(doc.empty());
  const size_t job_row = doc.find("| `rules[].job` |");
  const size_t fill_row = doc.find("| `rules[].fill` |");
  ASSERT_NE(job_row, std::string::npos);
  ASSERT_NE(fill_row, std::string::npos);
  const std::string job_text =
      doc.substr(job_row, doc.find('\n', job_row) - job_row);
  const std::string fill_text =
      doc.substr(fill_row, doc.find('\n', fill_row) - fill_row);
  for (const auto& def : job::InterpolationOptionTable()) {
    if ((def.doors & job::kRulesFile) == 0) continue;
    EXPECT_THAT(job_text,
                HasSubstr(absl::StrCat("`", std::string(def.key), "`")))
        << "rules[].job does not document " << def.key;
  }
  for (const auto& def : job::FillOptionTable()) {
    if ((def.doors & job::kRulesFile) == 0) continue;
    EXPECT_THAT(fill_text,
                HasSubstr(absl::StrCat("`", std::string(def.key), "`")))
        << "rules[].fill does not document " << def.key;
  }
}

// The documented examples parse, so that they cannot rot.
TEST_F(ConfigTest, DocumentedExamplesParse) {
  const std::string dir =
      std::string(::interslice::testing::SourceDir()) + "/docs/examples";
  absl::StatusOr<PeersConfig> peers = LoadPeersConfig(dir + "/peers.yaml");
  ASSERT_TRUE(peers.ok()) << peers.status();
  EXPECT_GE(peers->peers.size(), 1u);
  absl::StatusOr<RuleSet> rules =
      LoadRulesFile(dir + "/rules.yaml", peers->peers);
  ASSERT_TRUE(rules.ok()) << rules.status();
  EXPECT_GE(rules->rules.size(), 1u);
  EXPECT_THAT(rules->rules[0].name, Not(HasSubstr("#")));
}

// Issue 25: a series no rule takes is explained rule by rule, with the
// first criterion that failed, and never with free-text values.
TEST_F(ConfigTest, NoMatchIsExplainedRuleByRule) {
  absl::StatusOr<RuleSet> set = LoadRulesFile(
      Write("explain.yaml",
            "rules:\n"
            "  - name: ct-bone\n"
            "    match: {modality: CT, called_ae: INTERSLICE}\n"
            "    job: {threshold: 300}\n"
            "  - name: head\n"
            "    match: {modality: MR, series_description: \"(?i)head\"}\n"
            "    job: {threshold: 100}\n"
            "  - name: thick\n"
            "    match: {modality: MR, slice_thickness: {min: 2.5},\n"
            "            slice_count: [10, 400]}\n"
            "    job: {threshold: 100}\n"
            "  - name: seg\n"
            "    match: {modality: SEG}\n"
            "    fill: {}\n"),
      Peers());
  ASSERT_TRUE(set.ok()) << set.status();
  SeriesFacts mr;
  mr.modality = "MR";
  mr.called_ae = "INTERSLICE";
  mr.series_description = "Doe^Jane brain";  // free text: never shown
  mr.slice_thickness_mm = 1.0;
  mr.slice_count = 3;
  ASSERT_EQ(set->FirstMatch(mr), nullptr);
  const std::string why = set->ExplainNoMatch(mr);
  EXPECT_EQ(why,
            "rule 'ct-bone': modality is 'MR', not 'CT'; "
            "rule 'head': series_description does not match /(?i)head/; "
            "rule 'thick': slice_thickness 1 not >= 2.5; "
            "rule 'seg': a fill rule (segmentations only)");
  EXPECT_THAT(why, Not(HasSubstr("Doe")));
  // The first failing criterion in the documented order: the AE title
  // before the thickness.
  SeriesFacts ct = mr;
  ct.modality = "ct ";  // case and spaces ignored
  ct.called_ae = "OTHER";
  EXPECT_THAT(set->ExplainNoMatch(ct),
              HasSubstr("rule 'ct-bone': called_ae is 'OTHER', not "
                        "'INTERSLICE'"));
  SeriesFacts unknown_thickness = mr;
  unknown_thickness.series_description = "head";
  unknown_thickness.slice_thickness_mm.reset();
  EXPECT_THAT(set->ExplainNoMatch(unknown_thickness),
              HasSubstr("rule 'head': matches; rule 'thick': "
                        "slice_thickness unknown, wanted >= 2.5"));
  SeriesFacts seg;
  seg.modality = "SEG";
  seg.segmentation = true;
  EXPECT_THAT(set->ExplainNoMatch(seg),
              HasSubstr("rule 'ct-bone': a job rule (not for segmentations)"));
  EXPECT_EQ(set->rules[2].match.Describe(),
            "modality MR, slice_thickness >= 2.5, slice_count in [10, 400]");
  EXPECT_EQ(set->rules[3].match.Describe(), "modality SEG");
}

}  // namespace
}  // namespace interslice::server::node
