#include <gtest/gtest.h>

#include "config_file.h"
#include "core/errors.h"

using namespace brainshift;

namespace {

// The error message of parsing `text` as bad.toml, or "no error".
std::string message_of(const std::string& text) {
  try {
    config::pipeline_parameters_from_text(text, "bad.toml");
  } catch (const InputError& e) {
    return e.what();
  }
  return "no error";
}

}  // namespace

TEST(Config, DefaultsParseAndMatchTheDocumentedTable) {
  const auto p = config::pipeline_parameters_from_text(config::default_config_text(), "built-in");
  ASSERT_EQ(p.label_table.entries.size(), 4u);
  EXPECT_EQ(p.label_table.brain_label(), 1);
  EXPECT_EQ(p.label_table.cavity_labels(), std::vector<std::uint16_t>{2});
  EXPECT_EQ(p.label_table.find("corticospinal_tract")->value, 3);
  EXPECT_EQ(p.label_table.find("tumor")->value, 4);
  EXPECT_DOUBLE_EQ(p.label_table.find(1)->youngs_modulus_pa, 3000.0);
  EXPECT_DOUBLE_EQ(p.label_table.find(1)->poisson_ratio, 0.35);
  // The one copy of the defaults is labels.toml: the compiled-in table is it.
  EXPECT_EQ(config::default_label_table().entries.size(), p.label_table.entries.size());
  EXPECT_EQ(short_name_of(*p.label_table.find("corticospinal_tract")), "cst");
  EXPECT_EQ(short_name_of(*p.label_table.find("ventricles")), "ventricles");
  EXPECT_EQ(p.elastic.solver, SolverKind::direct_cholesky);
  EXPECT_EQ(p.elastic.dirichlet, DirichletMethod::symmetric_elimination);
}

TEST(Config, ValuesOverrideDefaults) {
  const auto p = config::pipeline_parameters_from_text(
      "[mesh]\ncell_size_mm = 5.5\n[elastic]\nsolver = \"cg_gamg\"\n[surface.outer]\nmembrane_stiffness = 3.0\n", "t");
  EXPECT_DOUBLE_EQ(p.meshing.cell_size_mm, 5.5);
  EXPECT_EQ(p.elastic.solver, SolverKind::cg_gamg);
  EXPECT_DOUBLE_EQ(p.outer_surface.membrane_stiffness, 3.0);
}

TEST(Config, TyposAndBadValuesAreErrorsNamingTheKey) {
  EXPECT_NE(message_of("[mesh]\ncell_sise_mm = 3\n").find("cell_sise_mm"), std::string::npos);
  EXPECT_NE(message_of("[mesh]\ncell_size_mm = \"big\"\n").find("cell_size_mm"), std::string::npos);
  EXPECT_NE(message_of("[elastic]\nsolver = \"magic\"\n").find("magic"), std::string::npos);
  EXPECT_NE(message_of("[nonsense]\nx = 1\n").find("nonsense"), std::string::npos);
  EXPECT_NE(message_of("[mesh\n").find("bad.toml"), std::string::npos);
}

TEST(Config, LabelTableValidation) {
  const char* two_parenchyma =
      "[[label]]\nvalue = 1\nname = \"a\"\nrole = \"parenchyma\"\n"
      "[[label]]\nvalue = 2\nname = \"b\"\nrole = \"parenchyma\"\n";
  EXPECT_THROW(config::label_table_from_text(two_parenchyma, "t"), InputError);
  const char* bad_nu = "[[label]]\nvalue = 1\nname = \"a\"\nrole = \"parenchyma\"\npoisson_ratio = 0.5\n";
  EXPECT_THROW(config::label_table_from_text(bad_nu, "t"), InputError);
  const char* duplicate = "[[label]]\nvalue = 1\nname = \"a\"\nrole = \"parenchyma\"\n"
                          "[[label]]\nvalue = 1\nname = \"b\"\n";
  EXPECT_THROW(config::label_table_from_text(duplicate, "t"), InputError);
  const char* bad_role = "[[label]]\nvalue = 1\nname = \"a\"\nrole = \"bone\"\n";
  EXPECT_THROW(config::label_table_from_text(bad_role, "t"), InputError);
  const char* custom = "[[label]]\nvalue = 7\nname = \"cortex\"\nrole = \"parenchyma\"\nyoungs_modulus_pa = 2000.0\n"
                       "[[label]]\nvalue = 9\nname = \"csf\"\nrole = \"cavity\"\n";
  const auto t = config::label_table_from_text(custom, "t");
  EXPECT_EQ(t.brain_label(), 7);
  EXPECT_EQ(t.cavity_labels(), std::vector<std::uint16_t>{9});
  EXPECT_TRUE(t.resectable_labels().empty());
  const char* resectable = "[[label]]\nvalue = 1\nname = \"a\"\nrole = \"parenchyma\"\n"
                           "[[label]]\nvalue = 5\nname = \"glioma\"\nrole = \"structure\"\nresectable = true\n";
  EXPECT_EQ(config::label_table_from_text(resectable, "t").resectable_labels(), std::vector<std::uint16_t>{5});
  const char* resectable_cavity = "[[label]]\nvalue = 1\nname = \"a\"\nrole = \"parenchyma\"\n"
                                  "[[label]]\nvalue = 2\nname = \"v\"\nrole = \"cavity\"\nresectable = true\n";
  EXPECT_THROW(config::label_table_from_text(resectable_cavity, "t"), InputError);
  // The default table: the tumor may be resected, nothing else.
  EXPECT_EQ(config::default_label_table().resectable_labels(), std::vector<std::uint16_t>{4});
  EXPECT_EQ(config::pipeline_parameters_from_text(config::default_config_text(), "built-in")
                .label_table.resectable_labels(),
            std::vector<std::uint16_t>{4});
}

// A name becomes a file (models/<name>.vtp) and a frame name; a short name an
// OpenIGTLink device name (20 bytes with "bs.model.").
TEST(Config, LabelNamesAreSafeAndShortNamesFitOpenIgtlink) {
  auto table = [](const std::string& fifth) {
    return "[[label]]\nvalue = 1\nname = \"brain\"\nrole = \"parenchyma\"\n[[label]]\nvalue = 5\n" + fifth;
  };
  const auto ok = config::label_table_from_text(table("name = \"arcuate_fasciculus\"\nshort_name = \"af\"\n"), "t");
  EXPECT_EQ(short_name_of(*ok.find(5)), "af");
  EXPECT_EQ(short_name_of(*config::label_table_from_text(table("name = \"arcuate_fasciculus\"\n"), "t").find(5)),
            "arcuate_fas");
  for (const char* bad : {"name = \"../x\"\n", "name = \"Arcuate\"\n", "name = \"5af\"\n",
                          "name = \"a.b\"\n", "name = \"af\"\nshort_name = \"arcuate_fasc\"\n",
                          "name = \"af\"\nshort_name = \"brain\"\n"})
    EXPECT_THROW(config::label_table_from_text(table(bad), "t"), InputError) << bad;
}

// labels.get serves at most 64 labels (PROTOCOL.md 5.6), as a label map names
// at most 64 structures: a larger table is refused when it is read.
TEST(Config, LabelTableHoldsAtMostWhatTheProtocolCanName) {
  std::string text = "[[label]]\nvalue = 1\nname = \"brain\"\nrole = \"parenchyma\"\n";
  for (int v = 2; v <= 64; ++v)
    text += "[[label]]\nvalue = " + std::to_string(v) + "\nname = \"s" + std::to_string(v) + "\"\n";
  EXPECT_EQ(config::label_table_from_text(text, "t").entries.size(), 64u);
  text += "[[label]]\nvalue = 65\nname = \"s65\"\n";
  EXPECT_THROW(config::label_table_from_text(text, "t"), InputError);
}

// Colours drawn in report.png and the Slicer scene: labels.toml's; a missing
// colour gets the palette's; a malformed one names the file and the label.
TEST(Config, LabelColoursParseDefaultAndFailClearly) {
  const auto file = config::pipeline_parameters_from_text(config::default_config_text(), "built-in").label_table;
  EXPECT_EQ(file.find("brain")->colour, (LabelColour{40, 220, 60}));
  EXPECT_EQ(file.find("tumor")->colour, (LabelColour{255, 230, 0}));
  const auto t = config::label_table_from_text(
      "[[label]]\nvalue = 1\nname = \"a\"\nrole = \"parenchyma\"\ncolour = \"#0A0b0C\"\n"
      "[[label]]\nvalue = 5\nname = \"arcuate\"\n", "t");
  EXPECT_EQ(t.find(1)->colour, (LabelColour{10, 11, 12}));
  EXPECT_EQ(t.find(5)->colour, default_label_colour(5));
  EXPECT_EQ(to_hex(LabelColour{10, 11, 255}), "#0a0bff");
  for (const char* bad : {"red", "#12345", "#1234567", "#12345g"}) {
    const std::string text =
        std::string("[[label]]\nvalue = 1\nname = \"a\"\nrole = \"parenchyma\"\ncolour = \"") + bad + "\"\n";
    try {
      config::label_table_from_text(text, "lab.toml");
      ADD_FAILURE() << bad << " was accepted";
    } catch (const InputError& e) {
      const std::string m = e.what();
      EXPECT_NE(m.find("lab.toml"), std::string::npos) << m;
      EXPECT_NE(m.find(bad), std::string::npos) << m;
    }
  }
}

TEST(Config, IntensitySectionDefaultsMatchTheEngineAndOverride) {
  const auto file = config::pipeline_parameters_from_text(config::default_config_text(), "built-in").intensity;
  const IntensityRefinementParameters code;  // the file documents the engine's defaults, not other values
  EXPECT_EQ(file.enabled, code.enabled);
  EXPECT_DOUBLE_EQ(file.lattice_spacing_mm, code.lattice_spacing_mm);
  EXPECT_EQ(file.iterations, code.iterations);
  EXPECT_DOUBLE_EQ(file.convergence_mm, code.convergence_mm);
  EXPECT_DOUBLE_EQ(file.membrane_weight, code.membrane_weight);
  EXPECT_DOUBLE_EQ(file.shrink_weight_per_mm2, code.shrink_weight_per_mm2);
  EXPECT_DOUBLE_EQ(file.smoothing_length_mm, code.smoothing_length_mm);
  EXPECT_DOUBLE_EQ(file.fem_trust_length_mm, code.fem_trust_length_mm);
  EXPECT_EQ(file.match_point_spread, code.match_point_spread);
  EXPECT_DOUBLE_EQ(file.max_correction_mm, code.max_correction_mm);
  EXPECT_DOUBLE_EQ(file.max_step_mm, code.max_step_mm);
  EXPECT_DOUBLE_EQ(file.sample_spacing_mm, code.sample_spacing_mm);
  EXPECT_EQ(file.max_samples, code.max_samples);
  EXPECT_DOUBLE_EQ(file.boundary_margin_mm, code.boundary_margin_mm);
  EXPECT_DOUBLE_EQ(file.robust_scale, code.robust_scale);
  EXPECT_EQ(file.bias_degree, code.bias_degree);
  EXPECT_DOUBLE_EQ(file.outside_fade_mm, code.outside_fade_mm);
  EXPECT_DOUBLE_EQ(file.min_explained_variance, code.min_explained_variance);

  const auto p = config::pipeline_parameters_from_text(
      "[intensity]\nenabled = false\nlattice_spacing_mm = 6.0\niterations = 4\nmax_samples = 20000\nbias_degree = 0\n",
      "t").intensity;
  EXPECT_FALSE(p.enabled);
  EXPECT_DOUBLE_EQ(p.lattice_spacing_mm, 6.0);
  EXPECT_EQ(p.iterations, 4);
  EXPECT_EQ(p.max_samples, 20000u);
  EXPECT_EQ(p.bias_degree, 0);
}

TEST(Config, BadIntensityValuesAreErrorsNamingSectionAndKey) {
  const std::string spacing = message_of("[intensity]\nlattice_spacing_mm = 0.5\n");
  EXPECT_NE(spacing.find("bad.toml"), std::string::npos) << spacing;
  EXPECT_NE(spacing.find("[intensity]"), std::string::npos) << spacing;
  EXPECT_NE(spacing.find("lattice_spacing_mm"), std::string::npos) << spacing;
  EXPECT_NE(message_of("[intensity]\nbias_degree = 5\n").find("bias_degree"), std::string::npos);
  EXPECT_NE(message_of("[intensity]\nmin_explained_variance = 1.0\n").find("min_explained_variance"), std::string::npos);
  EXPECT_NE(message_of("[intensity]\nshrink_weight_per_mm2 = 0.0\n").find("shrink_weight_per_mm2"), std::string::npos);
  EXPECT_NE(message_of("[intensity]\nsmoothing_length_mm = -1.0\n").find("smoothing_length_mm"), std::string::npos);
  EXPECT_NE(message_of("[intensity]\nfem_trust_length_mm = 0.0\n").find("fem_trust_length_mm"), std::string::npos);
  EXPECT_NE(message_of("[intensity]\nmax_samples = -3\n").find("max_samples"), std::string::npos);
  EXPECT_NE(message_of("[intensity]\nlatice_spacing_mm = 8.0\n").find("latice_spacing_mm"), std::string::npos);
  EXPECT_NE(message_of("[intensity]\nenabled = \"yes\"\n").find("enabled"), std::string::npos);
}

TEST(Config, SurfaceRepairAndSelfContactAreConfiguredWithTheEnginesDefaults) {
  const auto p = config::pipeline_parameters_from_text(config::default_config_text(), "built-in");
  const SurfaceRepairParameters engine;
  EXPECT_EQ(p.surface_repair.enabled, engine.enabled);
  EXPECT_DOUBLE_EQ(p.surface_repair.unreliable_residual_mm, engine.unreliable_residual_mm);
  EXPECT_EQ(p.surface_repair.rounds, engine.rounds);
  EXPECT_DOUBLE_EQ(p.surface_repair.min_component_area_mm2, engine.min_component_area_mm2);
  EXPECT_DOUBLE_EQ(p.surface_repair.smoothing_mm, engine.smoothing_mm);
  EXPECT_DOUBLE_EQ(p.surface_repair.max_search_mm, engine.max_search_mm);
  EXPECT_EQ(p.outer_surface.stiffness_levels, 2);
  EXPECT_DOUBLE_EQ(p.outer_surface.normal_search_mm, 12.0);
  EXPECT_EQ(p.ventricle_surface.stiffness_levels, 2);
  EXPECT_TRUE(p.outer_surface.fold_guard_enabled);
  EXPECT_DOUBLE_EQ(p.outer_surface.fold_guard.max_normal_turn_deg, FoldGuard{}.max_normal_turn_deg);
  EXPECT_DOUBLE_EQ(p.gates.max_unsupported_displacement_mm, QualityGates{}.max_unsupported_displacement_mm);
  EXPECT_DOUBLE_EQ(p.outer_surface.contact_fraction, 0.4);
  EXPECT_DOUBLE_EQ(p.ventricle_surface.contact_fraction, 0.4);
  EXPECT_DOUBLE_EQ(p.ventricle_surface.capture_range_mm, 6.0);
  EXPECT_DOUBLE_EQ(p.outer_surface.capture_range_mm, 0.0);
  const auto off = config::pipeline_parameters_from_text(
      "[surface.repair]\nenabled = false\n[surface.ventricles]\ncontact_fraction = 0.2\nmax_normal_turn_deg = 60.0\n", "t");
  EXPECT_FALSE(off.surface_repair.enabled);
  EXPECT_DOUBLE_EQ(off.ventricle_surface.fold_guard.max_normal_turn_deg, 60.0);
  EXPECT_DOUBLE_EQ(off.ventricle_surface.contact_fraction, 0.2);
  EXPECT_NE(message_of("[surface.repair]\nrounds = 0\n").find("[surface.repair]"), std::string::npos);
  // The repaired-area limit is gone (reported, not a gate): an old file saying it is told so.
  EXPECT_NE(message_of("[surface.repair]\nmax_defect_area_fraction = 0.15\n").find("max_defect_area_fraction"),
            std::string::npos);
  EXPECT_NE(message_of("[surface.outer]\nmax_normal_turn_deg = 90.0\n").find("max_normal_turn_deg"), std::string::npos);
  EXPECT_NE(message_of("[surface.repair]\nsmoothing_mm = 20.0\nmax_search_mm = 30.0\n").find("max_search_mm"),
            std::string::npos);
  EXPECT_NE(message_of("[surface.repair]\nringz = 2\n").find("ringz"), std::string::npos);
  EXPECT_NE(message_of("[surface.ventricles]\ncontact_fraction = 1.0\n").find("contact_fraction"), std::string::npos);
}

// The shipped file, with the tables of brainshiftd ([server]...) and of
// brainshift-dicom-node ([dicom_node]) the pipeline's reader must let through.
TEST(ConfigFile, ShippedBrainshiftdTomlIsAccepted) {
  EXPECT_NO_THROW(config::pipeline_parameters_from_file(BRAINSHIFT_SOURCE_DIR "/config/brainshiftd.toml"));
}

// [auto_segmentation]: the shipped file documents the engine's defaults (an
// image-only scan behaves the same with or without it), values override, and
// a bad value is refused naming the section and key.
TEST(Config, AutoSegmentationDefaultsMatchTheEngineAndOverride) {
  const auto file = config::pipeline_parameters_from_text(config::default_config_text(), "built-in").auto_segmentation;
  const AutoSegmentationParameters code;
  EXPECT_DOUBLE_EQ(file.prior_width_affine_mm, code.prior_width_affine_mm);
  EXPECT_DOUBLE_EQ(file.prior_width_nonrigid_mm, code.prior_width_nonrigid_mm);
  EXPECT_DOUBLE_EQ(file.ventricle_shift_affine_mm, code.ventricle_shift_affine_mm);
  EXPECT_DOUBLE_EQ(file.prior_inward_width_affine_mm, code.prior_inward_width_affine_mm);
  EXPECT_DOUBLE_EQ(file.prior_inward_width_nonrigid_mm, code.prior_inward_width_nonrigid_mm);
  EXPECT_EQ(file.bright_fluid_bias_degree_affine, code.bright_fluid_bias_degree_affine);
  EXPECT_DOUBLE_EQ(file.ventricle_prior_width_mm, code.ventricle_prior_width_mm);
  EXPECT_DOUBLE_EQ(file.working_spacing_mm, code.working_spacing_mm);
  EXPECT_EQ(file.rematch_rounds, code.rematch_rounds);
  EXPECT_EQ(file.rematch_reuses_fit, code.rematch_reuses_fit);
  EXPECT_DOUBLE_EQ(file.max_brain_volume_change, code.max_brain_volume_change);
  EXPECT_DOUBLE_EQ(file.min_ventricle_fraction, code.min_ventricle_fraction);
  EXPECT_DOUBLE_EQ(file.min_surface_confidence, code.min_surface_confidence);
  EXPECT_DOUBLE_EQ(file.max_uncertain_surface_fraction, code.max_uncertain_surface_fraction);
  EXPECT_EQ(file.check_given_labels, code.check_given_labels);
  EXPECT_EQ(file.given_labels, code.given_labels);
  for (const auto* c : {&file.classifier, &file.label_image_check.classifier}) {
    EXPECT_DOUBLE_EQ(c->prior_floor, code.classifier.prior_floor);
    EXPECT_DOUBLE_EQ(c->margin_mm, code.classifier.margin_mm);
    EXPECT_DOUBLE_EQ(c->min_fluid_contrast_sd, code.classifier.min_fluid_contrast_sd);
    EXPECT_DOUBLE_EQ(c->max_sulcus_half_width_mm, code.classifier.max_sulcus_half_width_mm);
    EXPECT_DOUBLE_EQ(c->max_cap_mm, code.classifier.max_cap_mm);
    EXPECT_DOUBLE_EQ(c->min_gap_ml, code.classifier.min_gap_ml);
    EXPECT_DOUBLE_EQ(c->max_gap_median_toward_fluid_turn, code.classifier.max_gap_median_toward_fluid_turn);
    EXPECT_DOUBLE_EQ(c->min_gap_preop_toward_tissue, code.classifier.min_gap_preop_toward_tissue);
    EXPECT_DOUBLE_EQ(c->max_fluid_rim_mm, code.classifier.max_fluid_rim_mm);
    EXPECT_DOUBLE_EQ(c->max_rim_cap_mm, code.classifier.max_rim_cap_mm);
    EXPECT_DOUBLE_EQ(c->rim_cap_cavity_margin_mm, code.classifier.rim_cap_cavity_margin_mm);
    EXPECT_EQ(c->em.bias_degree, code.classifier.em.bias_degree);
    EXPECT_EQ(c->em.max_iterations, code.classifier.em.max_iterations);
    EXPECT_DOUBLE_EQ(c->em.tolerance, code.classifier.em.tolerance);
    EXPECT_EQ(c->em.fit_samples, code.classifier.em.fit_samples);
    EXPECT_DOUBLE_EQ(c->em.mrf_beta, code.classifier.em.mrf_beta);
    EXPECT_EQ(c->em.mrf_sweeps, code.classifier.em.mrf_sweeps);
    EXPECT_EQ(c->sharpening_bias, code.classifier.sharpening_bias);
    EXPECT_DOUBLE_EQ(c->sharpening.smoothing_mm, code.classifier.sharpening.smoothing_mm);
    EXPECT_EQ(c->sharpening.max_iterations, code.classifier.sharpening.max_iterations);
  }
  EXPECT_DOUBLE_EQ(file.label_image_check.prior_width_mm, code.label_image_check.prior_width_mm);
  EXPECT_DOUBLE_EQ(file.label_image_check.min_posterior, code.label_image_check.min_posterior);
  EXPECT_DOUBLE_EQ(file.label_image_check.band_mm, code.label_image_check.band_mm);
  EXPECT_DOUBLE_EQ(file.label_image_check.max_disagreement_fraction,
                   code.label_image_check.max_disagreement_fraction);

  const auto p = config::pipeline_parameters_from_text(
      "[auto_segmentation]\nrematch_rounds = 0\ncheck_given_labels = false\ngiven_labels = \"exact\"\n"
      "[auto_segmentation.classifier]\nmrf_beta = 0.0\nbias_degree = 1\nsharpening_bias = true\n"
      "[auto_segmentation.label_check]\nband_mm = 2.0\n",
      "t").auto_segmentation;
  EXPECT_EQ(p.rematch_rounds, 0);
  EXPECT_FALSE(p.check_given_labels);
  EXPECT_EQ(p.given_labels, GivenLabelsUse::exact);
  EXPECT_DOUBLE_EQ(p.classifier.em.mrf_beta, 0.0);
  EXPECT_EQ(p.classifier.em.bias_degree, 1);
  EXPECT_TRUE(p.classifier.sharpening_bias);
  EXPECT_EQ(p.label_image_check.classifier.em.bias_degree, 1);  // one classifier for both paths
  EXPECT_DOUBLE_EQ(p.label_image_check.band_mm, 2.0);
}

TEST(Config, BadAutoSegmentationValuesAreErrorsNamingSectionAndKey) {
  const std::string volume = message_of("[auto_segmentation]\nmax_brain_volume_change = 1.5\n");
  EXPECT_NE(volume.find("[auto_segmentation]"), std::string::npos) << volume;
  EXPECT_NE(volume.find("max_brain_volume_change"), std::string::npos) << volume;
  EXPECT_NE(message_of("[auto_segmentation]\nrematch_rounds = 9\n").find("rematch_rounds"), std::string::npos);
  EXPECT_NE(message_of("[auto_segmentation]\nworking_spacing_mm = -1\n").find("working_spacing_mm"), std::string::npos);
  EXPECT_NE(message_of("[auto_segmentation]\nprior_width_affine_mm = 0\n").find("prior_width_affine_mm"),
            std::string::npos);
  EXPECT_NE(message_of("[auto_segmentation]\nventricle_shift_affine_mm = -1\n").find("ventricle_shift_affine_mm"),
            std::string::npos);
  EXPECT_NE(message_of("[auto_segmentation]\ncheck_given_labels = 1\n").find("check_given_labels"),
            std::string::npos);
  EXPECT_NE(message_of("[auto_segmentation]\ngiven_labels = \"mostly\"\n").find("given_labels"), std::string::npos);
  const std::string floor = message_of("[auto_segmentation.classifier]\nprior_floor = 0.7\n");
  EXPECT_NE(floor.find("auto_segmentation.classifier"), std::string::npos) << floor;
  EXPECT_NE(floor.find("prior_floor"), std::string::npos) << floor;
  EXPECT_NE(message_of("[auto_segmentation.classifier]\nmax_iterations = 0\n").find("max_iterations"),
            std::string::npos);
  EXPECT_NE(message_of("[auto_segmentation.label_check]\nmin_posterior = 0.3\n").find("min_posterior"),
            std::string::npos);
  EXPECT_NE(message_of("[auto_segmentation]\nprior_widht_mm = 3\n").find("prior_widht_mm"), std::string::npos);
}
