#pragma once
// Automatic segmentation of an intraop MR image guided by the patient's own
// preop labels (tissue_em.h): the preop labels carried onto the intraop grid
// become the prior, the image decides where tissue really is now.
// Output in the label table's values: the parenchyma label for brain tissue
// (everything inside the brain but the ventricles), the ventricle label for
// the lateral ventricles, 0 outside the brain and in a resection cavity; and
// per voxel the posterior of the tissue chosen (the confidence).
#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <nlohmann/json.hpp>

#include "core/image.h"
#include "segmentation/open_fluid.h"
#include "segmentation/sharpening_bias.h"
#include "segmentation/tissue_em.h"

namespace brainshift::segmentation {

struct SegmentationParameters {
  // Remaining misregistration of the carried labels (mm), the prior's width
  // (tissue_prior.h). The caller sets it per round: wider after the affine
  // alone, narrower once the non-rigid estimate carries the labels.
  double prior_width_mm = 3.0;
  // Inside the carried outline (tissue_prior.h PriorWidths::inward_mm); 0:
  // the same as prior_width_mm.
  double prior_inward_width_mm = 0;
  // The same for the ventricles (tissue_prior.h). They are a few mm across,
  // so a width beyond their own misregistration spreads a single fluid class
  // over white matter; below it, their fluid where they moved to is
  // classified as tissue. The caller sets it per round.
  double ventricle_prior_width_mm = 2.0;
  // How far the ventricles may have moved from the carried ones (mm; 0 when
  // the carried labels already follow the brain's shift): tissue_prior.h.
  double ventricle_shift_mm = 0;
  // Every tissue keeps at least this prior probability anywhere: 1e-3 costs
  // log(1e-3) = -6.9 nats, what an intensity about 3.7 class sd's closer to
  // another tissue's mean outweighs, so the image overrules a prior that
  // brain shift has made wrong (fluid where the preop had cortex).
  double prior_floor = 1e-3;
  // The classification runs in the carried outline's bounding box grown by
  // this margin: wider than the largest brain shift measured at the cortex
  // (about 25 mm, docs/DESIGN.md "Automatic intraop segmentation"). The
  // image-only rounds set it to where their prior meets the floor
  // (prior_reach_mm, tissue_prior.h).
  double margin_mm = 30;
  EmParameters em;
  // The shading found from the histogram before the classes are fitted
  // (sharpening_bias.h). Off by default: it takes an unnormalised receive
  // array's shading out (8 loops, image only: 10 of 13 scans non-rigid at
  // 0.83 mm mean instead of 8 at 1.99, no answer worse than uncorrected),
  // but on real anatomy it reads the partial volume of the cortex's rim as
  // a darkening there and the segmented brain grows by about half a
  // millimetre (the robustness suite 0.351 -> 0.415 mm). For sites whose
  // intraop series are not intensity-normalised (docs/DESIGN.md "Automatic
  // intraop segmentation", item 17).
  bool sharpening_bias = false;
  SharpeningBiasParameters sharpening;
  // Enclosed holes of the segmented brain smaller than this (ml) are noise
  // and filled; larger ones are kept as cavities (the pipeline passes its
  // min_resection_cavity_ml, so what is filled here would be ignored there).
  double max_filled_hole_ml = 0.1;
  // Fluid labelled brain that is thicker than twice this (mm) and open to the
  // outside is moved out of the brain (open_fluid.h):
  // sulci are 1-3 mm wide, up to about 4 with atrophy, while the gap under a
  // sunken cortex is as deep as the sinking (5-25 mm) and a cavity as wide as
  // what was resected. 0: off.
  double max_sulcus_half_width_mm = 2.5;
  // What lies beyond that fluid (between it and the outside) and is thinner
  // than this (mm) is the dura and inner table's partial volume, not brain:
  // slices up to 3 mm thick cut the inner table obliquely over the vertex
  // and spread it over three or four slices, while every lobe is more than
  // 20 mm across.
  double max_cap_mm = 10;
  // And that fluid holds at least this much (ml): the smallest gap that moves
  // the outline, a sinking deeper than a sulcus is wide (5 mm) under the
  // smallest craniotomy (about 5 cm across), a dome of about 5 ml; the basal
  // and sylvian cisterns, thick fluid open to the outside as well, hold a
  // few ml each and stay in the brain's outline as every outline counts them.
  double min_gap_ml = 5;
  // And that fluid is a body of fluid: the median of its bias-corrected
  // intensities lies less than this share of the way from the fluid class's
  // mean to where the fluid test turns (the nearest parenchyma class's side).
  // Fluid throughout has its median at the fluid's intensity (0, or beyond
  // it: the class also holds the ventricles' partial-volume wall); tissue
  // whose voxels hold part fluid passes the test only where noise carries
  // a voxel across the turn, and its median lies at the turn (1). Halfway
  // between the two (docs/DESIGN.md "Automatic intraop segmentation" item
  // 7; measured: gaps, cavities and cisterns -0.81..0.19, sheets of
  // partial-volume cortex 0.53-0.73). Infinity: off.
  double max_gap_median_toward_fluid_turn = 0.5;
  // And the preop, seen through the head's placement (PreopSeen), held
  // tissue there: the median of its intensities over the component lies at
  // least this share of the way from the preop's fluid (its ventricles'
  // median) to its tissue (its parenchyma's median). A sinking's gap opens
  // where the cortex was (grey matter: about 0.8 of the way in a T1), while
  // the basal cisterns and the fissures are fluid in the preop as well
  // (0-0.3): halfway between, as for the intraop test above (docs/DESIGN.md
  // "Automatic intraop segmentation", item 7). What the preop labels as
  // resectable counts as tissue: a cavity is a gap even where a cyst was.
  // 0: off.
  double min_gap_preop_toward_tissue = 0.5;
  // In an image whose fluid is the brightest tissue (T2-like), brain voxels
  // at least half fluid reached from the outside within this depth (mm) are
  // the CSF rim between cortex and skull, not brain (segmentation/fluid_rim.h):
  // the subarachnoid space over the convexity is 1-3 mm thick. Deeper fluid
  // open to the outside is the open-fluid rule's. 0: off. No effect on an
  // image whose fluid is dark (T1, FLAIR).
  double max_fluid_rim_mm = 3.0;
  // A cap over the rim (fluid_rim.h) may be thicker than the rim itself, up
  // to this (mm): the fluid-bone mixture beyond the vertex's fluid is 4-5 mm
  // of tissue-dark voxels (docs/PERFORMANCE.md 12.38); thinner than a gyrus,
  // two cortices of about 2.5 mm; and only voxels darker than the cortex can
  // be (a gyrus's crown over a sulcus's fluid is grey matter). The fluid such
  // a cap hides is looked for as deep under the outline as the rim and the
  // cap together. 0: the rim's own depth (the pipeline's first round, under
  // the head placement's wide prior; docs/DESIGN.md "Automatic intraop
  // segmentation", item 11).
  double max_rim_cap_mm = 5.0;
  // Except within this (mm) of the preop's resectable tissue where the head
  // placed it (PreopSeen::resectable): beside a resection cavity the brain
  // does lie beyond fluid, the cavity's walls (12.38: a 5 mm cap everywhere
  // cost the resection cases 0.001-0.004 of Dice). The tumour's own shift and
  // the cavity's collapse are a few mm; deep structures move up to about
  // 10 mm under a large craniotomy.
  double rim_cap_cavity_margin_mm = 10.0;
  // The ventricular fluid class must stand this many pooled sd's from the
  // farthest major parenchyma class, or the image cannot show the ventricles
  // (a contrast with no fluid/tissue difference, or noise far beyond any
  // scanner's): two Gaussians 2 sd apart overlap by about a third.
  double min_fluid_contrast_sd = 2.0;
  // And the segmented ventricles' median this many robust sd's from the
  // tissue one to three voxels around them: beyond it the fluid's median lies
  // outside the middle half of the tissue around (and vice versa), and the
  // wall is where the intensity crosses between them; below it the crossing
  // is placed by noise. Lower than the class figure: the tissue around the
  // wall mixes white matter, the caudate's grey matter and partial volume.
  double min_wall_contrast_sd = 1.0;
};

struct IntraopSegmentation {
  LabelImage labels;   // image grid, table values
  ImageF confidence;   // posterior of the chosen tissue, [0, 1]
  ImageF bias;         // multiplicative bias fitted (1 outside the classified box)
  std::vector<GaussianClass> classes;  // image units
  // The fitted log bias on the grid of the box it was fitted in, and that
  // box's first voxel on the image grid: a later round reuses it anywhere.
  std::optional<LogBiasField> bias_field;
  std::array<int, 3> bias_origin{0, 0, 0};
  std::string refusal;  // why the image cannot be segmented; empty when it can
  nlohmann::json report;  // classes, iterations, volumes, contrast
  // Fluid moved out of the brain as thicker than a sulcus and open to the
  // outside (SegmentationParameters::max_sulcus_half_width_mm), and the gap
  // of such fluid the classification itself left outside the brain inside
  // the carried outline, ml: what the brain-volume gate allows for.
  double open_fluid_ml = 0;
  // Those voxels on the image grid (empty grid when the rule did not run):
  // a re-match keeps only gaps the round before found (segment_intraop).
  Mask open_fluid;
};

// carried_labels: the preop labels on the image's grid. brain_label is the
// parenchyma value written; ventricle_labels the cavity values (the first is
// written). InputError on mismatched grids or an empty carried brain.
// fitted: an earlier round's segmentation of the same image; its classes and
// bias are reused (classify_with_classes, no EM fit) under the new prior.
// gap_found_before: the open fluid an earlier round of the same image moved
// out (IntraopSegmentation::open_fluid); when given, only open fluid that
// touches it is moved out now (docs/DESIGN.md "Automatic intraop
// segmentation", item 7).
// preop_seen: when given, open fluid the preop held as fluid stays in the
// brain (SegmentationParameters::min_gap_preop_toward_tissue).
IntraopSegmentation segment_intraop(const ImageF& image, const LabelImage& carried_labels,
                                    std::uint16_t brain_label, const std::vector<std::uint16_t>& ventricle_labels,
                                    const SegmentationParameters& params, const IntraopSegmentation* fitted = nullptr,
                                    const Mask* gap_found_before = nullptr, const PreopSeen* preop_seen = nullptr);

}  // namespace brainshift::segmentation
