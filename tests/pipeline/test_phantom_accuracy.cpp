// The full pipeline on varied brain-shift phantoms made from the real Colin27
// brain, with the default configuration (published mesh size). The phantom's
// deformation is analytic (not our elastic model), so the truth is
// independent of the method under test.
//
// The bounds are what the method reaches today with a margin, kept as a guard
// against regressions; the project's targets (issue "Registration pipeline":
// mean TRE <= 1.0 mm, p95 <= 2.5 mm, >= 80 % of the error removed) are
// tracked in docs/PERFORMANCE.md. Measured on this suite with the intensity
// refinement: mean 0.34 mm (worst case 0.54), p95 over all landmarks 1.06 mm,
// worst case p95 3.2 mm (resection collapse), 91 % removed; without it 0.96,
// 2.51, 4.4 mm and 75 %.
#include <gtest/gtest.h>
#include <mpi.h>

#include <cstdio>
#include <filesystem>
#include <memory>

#include "atlas/default_atlas.h"
#include "config_file.h"
#include "phantom_evaluation.h"

using namespace brainshift;

namespace {

std::filesystem::path atlas_cache() {
  const char* dir = std::getenv("BRAINSHIFT_ATLAS_CACHE");
  return dir ? dir : "brainshift-atlas";
}

}  // namespace

TEST(PhantomAccuracy, StandardSuiteOnColin27) {
  const PipelineParameters params =
      config::pipeline_parameters_from_text(config::default_config_text(), "built-in");
  EngineSession session(MPI_COMM_WORLD, params);
  DefaultAtlas atlas = load_or_build_default_atlas(atlas_cache());
  session.load_preop(PreopInput{std::move(atlas.t1), std::move(atlas.labels)}, nullptr);
  ASSERT_GE(session.mesh().node_count(), 43584u) << "default mesh below the published size";

  const auto suite = standard_phantom_suite();
  ASSERT_GE(suite.size(), 6u);
  // Cases that resect a tumor run on the atlas with that tumor in it (its own
  // warm state, with the second system whose tumor wall is fixed).
  std::unique_ptr<EngineSession> tumor_session;
  auto session_for = [&](const PhantomSpec& spec) -> EngineSession& {
    if (!spec.preop_tumor) return session;
    PreopInput preop{session.preop().t1, session.preop().labels};
    implant_tumor(preop.t1, preop.labels, *spec.preop_tumor);
    tumor_session = std::make_unique<EngineSession>(MPI_COMM_WORLD, params);
    tumor_session->load_preop(std::move(preop), nullptr);
    return *tumor_session;
  };
  std::vector<evaluation::CaseResult> cases;
  nlohmann::json table = nlohmann::json::array();
  for (const auto& spec : suite) {
    cases.push_back(evaluation::evaluate_case(session_for(spec), spec));
    if (spec.preop_tumor && spec.resection.enabled) {
      const auto& resection = cases.back().metrics["resection"];
      EXPECT_EQ(resection.value("system", 0), 1) << spec.name << ": the resection was not modelled: " << resection.dump();
    }
    const auto& c = cases.back();
    table.push_back(evaluation::to_json(c));
    std::printf("%-28s uncorrected %5.2f mm | affine %5.2f mm | non-rigid mean %5.2f p95 %5.2f max %5.2f mm | %.3f s%s\n",
                c.name.c_str(), c.uncorrected_mean_mm, c.affine_mean_mm, c.nonrigid_mean_mm,
                c.nonrigid_p95_mm, c.nonrigid_max_mm, c.intraop_total_seconds, c.fallback ? " FALLBACK" : "");
    EXPECT_FALSE(c.fallback) << c.name << ": " << c.metrics.dump();
    EXPECT_EQ(c.metrics["refine"]["applied"], true) << c.name << ": " << c.metrics["refine"].dump();
    EXPECT_LE(c.nonrigid_mean_mm, 0.7 * c.affine_mean_mm) << c.name << ": not clearly better than the affine alone";
    EXPECT_LE(c.nonrigid_mean_mm, 0.8) << c.name;
    EXPECT_LE(c.nonrigid_p95_mm, 4.0) << c.name;
  }
  const auto s = evaluation::summarise(cases);
  std::printf("suite: mean TRE %.2f mm (affine %.2f, uncorrected %.2f), p95 over all landmarks %.2f mm, worst case p95 %.2f mm, %.0f %% of the error removed\n",
              s.mean_mm, s.affine_mean_mm, s.uncorrected_mean_mm, s.pooled_p95_mm, s.p95_mm, 100 * s.removed_fraction);
  EXPECT_LE(s.mean_mm, 0.5);
  EXPECT_LE(s.pooled_p95_mm, 1.5);
  EXPECT_LT(s.mean_mm, 0.5 * s.affine_mean_mm) << "the non-rigid step must beat the affine over the suite";
  EXPECT_GE(s.removed_fraction, 0.85);
  if (const char* out = std::getenv("BRAINSHIFT_ACCURACY_JSON")) {
    FILE* f = std::fopen(out, "w");
    if (f) {
      std::fprintf(f, "%s\n", table.dump(1).c_str());
      std::fclose(f);
    }
  }
}
