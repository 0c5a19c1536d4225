#include "client/remote/find_command.h"

#include <cstdio>

#include "CLI/CLI.hpp"
#include "absl/strings/str_cat.h"
#include "client/remote/remote_common.h"
#include "interslice/v1/interslice.grpc.pb.h"

namespace interslice::client::remote {

CLI::App* RegisterFind(CLI::App& app, FindArguments& args,
                       ConnectionOptions& connection) {
  CLI::App* find = app.add_subcommand(
      "find",
      "List the studies and series (with their UIDs) on a DICOM peer of the "
      "server (C-FIND), for `submit --pacs PEER --study UID --series UID`");
  find->add_option("--pacs", args.peer,
                   "The peer (a name from the server's --dicom-peers file)")
      ->required();
  find->add_option("--patient-id", args.patient_id,
                   "Patient ID (wildcards * and ? allowed)");
  find->add_option("--study-date", args.study_date,
                   "YYYYMMDD, or a range YYYYMMDD-YYYYMMDD (either end may "
                   "be left out)");
  find->add_option("--modality", args.modality,
                   "CT, MR, ...: studies that have it, and only those series");
  find->add_option("--accession", args.accession,
                   "Accession number (wildcards * and ? allowed)");
  find->add_option("--max-studies", args.max_studies,
                   "At most this many studies (default: the server's, 100)");
  AddConnectionOptions(*find, connection);
  return find;
}

int RunFind(const Connection& connection, const FindArguments& args) {
  if (args.max_studies < 0) return Fail("--max-studies must be >= 0");
  v1::FindRequest request;
  request.set_peer(args.peer);
  request.set_patient_id(args.patient_id);
  request.set_study_date(args.study_date);
  request.set_modality(args.modality);
  request.set_accession_number(args.accession);
  request.set_max_studies(args.max_studies);
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  // Two queries per study on the server's side, each within the peer's
  // timeout: a generous bound.
  SetTimeout(context, 600);
  v1::FindResponse response;
  const grpc::Status s = stub->Find(&context, request, &response);
  // The peer's failure (named in the message: "cannot associate with peer
  // NAME (...)"), not the server's: said as it is.
  if (s.error_code() == grpc::UNAVAILABLE &&
      s.error_message().find("peer " + request.peer() + " (") !=
          std::string::npos) {
    return Fail(s.error_message());
  }
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  for (const v1::FoundStudy& study : response.studies()) {
    std::printf("study %s  date %s  patient %s  accession %s  %s  \"%s\"\n",
                Printable(study.study_instance_uid()).c_str(),
                Printable(study.study_date()).c_str(),
                Printable(study.patient_id()).c_str(),
                Printable(study.accession_number()).c_str(),
                Printable(study.modalities_in_study()).c_str(),
                Printable(study.study_description()).c_str());
    for (const v1::FoundSeries& series : study.series()) {
      const std::string instances =
          series.instances() >= 0
              ? absl::StrCat(series.instances(), " instance(s)")
              : std::string("? instance(s)");
      std::printf("  series %s  %s  #%s  %s  \"%s\"\n",
                  Printable(series.series_instance_uid()).c_str(),
                  Printable(series.modality()).c_str(),
                  Printable(series.series_number()).c_str(), instances.c_str(),
                  Printable(series.series_description()).c_str());
    }
  }
  if (response.studies().empty()) {
    std::fprintf(stderr, "no study on peer %s matches\n",
                 request.peer().c_str());
  }
  if (response.truncated()) {
    std::fprintf(stderr,
                 "more matched than the caps (%d studies, %d series): the "
                 "first are listed; narrow the keys (or --max-studies)\n",
                 response.max_studies(), response.max_series());
  }
  return 0;
}

}  // namespace interslice::client::remote
