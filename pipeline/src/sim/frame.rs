//! One science frame: its drawn parameters, the sources, what the detector does, the header.
use ndarray::Array2;
use sofipol_calib::profile::Beam;
use sofipol_calib::{Frame, Header};

use super::foreground::{offset_position, StarForeground};
use super::pointing::mean_angle_deg;
use super::truth::{
    ComponentTruth, FieldStarTruth, FramePointing, FrameTruth, SimFrame, SourceTruth, TargetForeground, TargetTruth,
};
use super::{effects, psf, schedule, EffectKind, Simulator};
use crate::stokes::model::{beam_fluxes, companion_offset_px, normalized_difference, Polarization};

/// Per-frame parameters drawn before rendering.
struct FrameParams {
    posang: f64,
    phi: f64,
    header_off: [f64; 2],
    true_off: [f64; 2],
    transparency: f64,
    sky_level: f64,
    psf: psf::Psf,
    mjd: f64,
    pointing: FramePointing,
    /// Sky-frame polarization of the telescope (None: effect not listed).
    telescope: Option<Polarization>,
}
impl Simulator {
    pub(super) fn target_truth(&self, t: usize, frames: &[Vec<FrameTruth>]) -> TargetTruth {
        let b = &self.targets[t];
        TargetTruth {
            object: b.name.clone(),
            tpl_start: self.plan[t].tpl_start.clone(),
            ra_deg: self.plan[t].ra_deg,
            dec_deg: self.plan[t].dec_deg,
            separation_arcsec: b.separation_arcsec,
            pa_deg: b.pa_deg,
            components: self.component_truth(t),
            frames: frames.get(t).cloned().unwrap_or_default(),
            foreground: self.star_foreground(t).map(|stars| TargetForeground {
                q: stars[0].q,
                u: stars[0].u,
                stars,
            }),
            field_stars: self.field_star_truth(t),
        }
    }

    /// The foreground field at every star of target `t` (A, B, then its field stars, as
    /// [`Simulator::frame`] lists them), when `foreground_field` is listed and `t` is a
    /// binary (standards see none: their p, gamma are their totals). A sits at the
    /// sequence's RA and Dec, every other star at its separation and position angle from A
    /// along the great circle.
    pub(super) fn star_foreground(&self, t: usize) -> Option<Vec<StarForeground>> {
        let field = self.foreground.as_ref()?;
        if self.is_standard(t) {
            return None;
        }
        self.calls.hit(EffectKind::ForegroundField);
        let b = &self.targets[t];
        let (ra, dec) = (self.plan[t].ra_deg, self.plan[t].dec_deg);
        let stars = [
            ("A".to_string(), 0.0, 0.0),
            ("B".to_string(), b.separation_arcsec, b.pa_deg),
        ]
        .into_iter()
        .chain(
            b.field_star
                .iter()
                .enumerate()
                .map(|(i, f)| (format!("field{}", i + 1), f.separation_arcsec, f.pa_deg)),
        )
        .map(|(name, sep, pa)| {
            let (ra_s, dec_s) = offset_position(ra, dec, sep, pa);
            let p = field.at(ra_s, dec_s);
            StarForeground {
                name,
                ra_deg: ra_s,
                dec_deg: dec_s,
                q: p.q,
                u: p.u,
            }
        })
        .collect();
        Some(stars)
    }

    /// Truth of target `t`'s field stars: recorded when the scene lists `foreground_field`
    /// or has a `field_population` (empty otherwise, as truth.json always was).
    fn field_star_truth(&self, t: usize) -> Vec<FieldStarTruth> {
        let s = &self.scene;
        if !(s.has(EffectKind::ForegroundField) || s.field_population.is_some()) || self.is_standard(t) {
            return Vec::new();
        }
        let b = &self.targets[t];
        let ism = self.ism();
        let fg = self.star_foreground(t);
        let n_own = b.field_star.len() - self.drawn_k[t].len();
        b.field_star
            .iter()
            .enumerate()
            .map(|(i, f)| {
                let intrinsic = Polarization::from_p_gamma(f.p, f.gamma_deg);
                let mut sky = intrinsic.add(ism);
                if let Some(fg) = &fg {
                    sky = sky.add(Polarization {
                        q: fg[2 + i].q,
                        u: fg[2 + i].u,
                    });
                }
                FieldStarTruth {
                    name: format!("field{}", i + 1),
                    separation_arcsec: f.separation_arcsec,
                    pa_deg: f.pa_deg,
                    flux: f.flux,
                    k_mag: i.checked_sub(n_own).map(|j| self.drawn_k[t][j]),
                    intrinsic,
                    q: sky.q,
                    u: sky.u,
                    p: sky.p(),
                    gamma_deg: sky.gamma_deg(),
                }
            })
            .collect()
    }

    fn frame_params(&self, t: usize, k: usize) -> FrameParams {
        let s = &self.scene;
        let o = &s.observation;
        let nd = o.dithers;
        let (io, d) = (k / nd, k % nd);
        let posang = o.orientations_deg[io];
        let step = o.jitter_step_px.unwrap_or(self.profile.geometry.jitter_step_px);
        let header_off = [(d as f64 - (nd as f64 - 1.0) / 2.0) * step, 0.0];
        let key = (t as u64, k as u64);
        let true_off = if s.has(EffectKind::PointingError) {
            effects::pointing_error(
                &self.calls,
                s.seed,
                &s.pointing_error.clone().unwrap_or_default(),
                key,
                header_off,
            )
        } else {
            header_off
        };
        let transparency = if s.has(EffectKind::Transparency) {
            effects::transparency(&self.calls, s.seed, &s.transparency.clone().unwrap_or_default(), key)
        } else {
            1.0
        };
        let sky_level = if s.has(EffectKind::Sky) {
            effects::sky_level(&self.calls, s.seed, &s.sky.clone().unwrap_or_default(), key)
        } else {
            0.0
        };
        let psf = if s.has(EffectKind::Psf) {
            effects::frame_psf(
                &self.calls,
                s.seed,
                &s.psf.clone().unwrap_or_default(),
                key,
                self.scale(),
            )
        } else {
            psf::Psf::Point
        };
        let mjd = schedule::exposure_mjd(s, self.plan[t].mjd, k);
        let (start, end) = schedule::exposure_pointing(s, &self.plan[t], k);
        let pointing = FramePointing {
            start,
            end,
            parallactic_angle_deg: mean_angle_deg(start.parang_deg, end.parang_deg),
        };
        let telescope = s.has(EffectKind::TelescopePolarization).then(|| {
            effects::telescope_polarization(
                &self.calls,
                &s.telescope_polarization.clone().unwrap_or_default(),
                pointing.parallactic_angle_deg,
            )
        });
        FrameParams {
            posang,
            phi: if s.has(EffectKind::AnalyzerAngle) {
                effects::analyzer_angle(&self.calls, &s.analyzer_angle.clone().unwrap_or_default(), posang)
            } else {
                self.profile.angles.analyzer_angle_deg(posang)
            },
            header_off,
            true_off,
            transparency,
            sky_level,
            psf,
            mjd,
            pointing,
            telescope,
        }
    }

    /// Truth of target `t`'s components.
    fn component_truth(&self, t: usize) -> Vec<ComponentTruth> {
        let b = &self.targets[t];
        let ism = if self.is_standard(t) {
            Polarization::default()
        } else {
            self.ism()
        };
        let fg = self.star_foreground(t);
        [
            ("A", b.flux_a, b.p_a, b.gamma_a_deg),
            ("B", b.flux_b, b.p_b, b.gamma_b_deg),
        ]
        .into_iter()
        .enumerate()
        .map(|(i, (name, flux, p, g))| {
            let intrinsic = Polarization::from_p_gamma(p, g);
            let mut sky = intrinsic.add(ism);
            if let Some(fg) = &fg {
                sky = sky.add(Polarization { q: fg[i].q, u: fg[i].u });
            }
            ComponentTruth {
                name: name.into(),
                flux,
                intrinsic,
                q: sky.q,
                u: sky.u,
                p: sky.p(),
                gamma_deg: sky.gamma_deg(),
            }
        })
        .collect()
    }

    fn ism(&self) -> Polarization {
        if self.scene.has(EffectKind::InterstellarPolarization) {
            self.calls.hit(EffectKind::InterstellarPolarization);
            let c = self.scene.interstellar_polarization.clone().unwrap_or_default();
            Polarization::from_p_gamma(c.p, c.angle_deg)
        } else {
            Polarization::default()
        }
    }

    /// Simulate frame `k` (0-based exposure index) of target `t`.
    pub fn frame(&self, t: usize, k: usize) -> SimFrame {
        let s = &self.scene;
        let g = &self.profile.geometry;
        let (ny, nx) = (g.ny, g.nx);
        let b = &self.targets[t];
        let fp = self.frame_params(t, k);
        let mut img = Array2::<f32>::zeros((ny, nx));

        if s.has(EffectKind::Sky) {
            effects::sky(&self.calls, &mut img, fp.sky_level, &s.sky.clone().unwrap_or_default());
            if let Some(tel) = fp.telescope {
                // The sky's light passes the telescope's mirrors too.
                effects::telescope_polarization_sky(&self.calls, &mut img, g, normalized_difference(tel, fp.phi));
            }
        }

        // Sources: A, B and field stars, each as (name, offset from A in px, flux, pol).
        let [x_a, y_a] = super::primary_xy(b, g);
        let ism = if self.is_standard(t) {
            Polarization::default()
        } else {
            self.ism()
        };
        let (t_o, t_e) = if s.has(EffectKind::Throughput) {
            effects::throughput(&self.calls, &s.throughput.clone().unwrap_or_default())
        } else {
            (1.0, 1.0)
        };
        let inst = if s.has(EffectKind::InstrumentalPolarization) {
            effects::instrumental_polarization(&self.calls, &s.instrumental_polarization.clone().unwrap_or_default())
        } else {
            0.0
        };
        let mut srcs: Vec<(String, (f64, f64), f64, Polarization)> = vec![
            (
                "A".into(),
                (0.0, 0.0),
                b.flux_a,
                Polarization::from_p_gamma(b.p_a, b.gamma_a_deg),
            ),
            (
                "B".into(),
                companion_offset_px(b.separation_arcsec, b.pa_deg, fp.posang, self.scale()),
                b.flux_b,
                Polarization::from_p_gamma(b.p_b, b.gamma_b_deg),
            ),
        ];
        if self.is_standard(t) {
            srcs.truncate(1);
        }
        for (i, f) in b.field_star.iter().enumerate() {
            srcs.push((
                format!("field{}", i + 1),
                companion_offset_px(f.separation_arcsec, f.pa_deg, fp.posang, self.scale()),
                f.flux,
                Polarization::from_p_gamma(f.p, f.gamma_deg),
            ));
        }
        // Sources from this index on were drawn by `field_population`.
        let first_drawn = srcs.len() - self.drawn_k[t].len();
        // The foreground field at each source (same order: A, B, field stars).
        let fg = self.star_foreground(t);
        let mut sources = Vec::with_capacity(srcs.len());
        for (i, (name, (dx, dy), flux, pol)) in srcs.into_iter().enumerate() {
            // Sky frame: the source's own polarization, the ISM in front of it (uniform,
            // then the foreground field at the source), then the telescope's (M3 is in
            // front of the rotator: it does not turn with phi).
            let mut pol = pol.add(ism);
            if let Some(fg) = &fg {
                pol = pol.add(Polarization { q: fg[i].q, u: fg[i].u });
            }
            if let Some(tel) = fp.telescope {
                pol = pol.add(tel);
            }
            let (mut fo, mut fe) = beam_fluxes(flux * fp.transparency, pol, fp.phi, t_o, t_e);
            let tot = fo + fe;
            if inst != 0.0 && tot > 0.0 {
                // Instrumental polarization q_inst (instrument frame) adds to F at every
                // orientation: f_o,e = (f_o + f_e)/2 (1 +- (F + q_inst)). (A zero-flux
                // component stays zero, not 0/0.)
                let f = (fo - fe) / tot + inst;
                fo = 0.5 * tot * (1.0 + f);
                fe = 0.5 * tot * (1.0 - f);
            }
            let xo = x_a + fp.true_off[0] + dx;
            let yo = y_a + fp.true_off[1] + dy;
            let xe = xo + g.eo_offset_px[0];
            let ye = yo + g.eo_offset_px[1];
            // A drawn field star's wing is cut where it holds 0.5 ADU (psf::render_with_tail).
            let tail = if i >= first_drawn {
                psf::MOFFAT_TAIL.max(0.5 / flux.max(1e-300))
            } else {
                psf::MOFFAT_TAIL
            };
            // The focal mask stands before the Wollaston prism: the light a slit lets
            // through makes the o image in that slit's o strip and the e image in its e
            // strip, and nothing else. A star behind a bar (its o image on an e strip's
            // rows or between strips) leaves neither image, and a star at a slit's edge
            // loses the same part of both. Without a mask nothing is blocked.
            let strips = s.has(EffectKind::Strips) && g.has_mask();
            let open_for = |beam: Beam| move |y: usize| !strips || g.beam_of_row(y) == Some(beam);
            let stamp_o = self.render(fp.psf, xo, yo, tail);
            psf::add_stamp_rows(&mut img, &stamp_o, fo, open_for(Beam::Ordinary));
            // The e image has the o image's sub-pixel phase when the beam offset is a
            // whole number of pixels (SOFI: 167 px): reuse the stamp.
            let (ox, oy) = (g.eo_offset_px[0], g.eo_offset_px[1]);
            let stamp_e = if ox.fract() == 0.0 && oy.fract() == 0.0 && (xe - ox == xo) && (ye - oy == yo) {
                stamp_o.shifted(ox as i64, oy as i64)
            } else {
                self.render(fp.psf, xe, ye, tail)
            };
            psf::add_stamp_rows(&mut img, &stamp_e, fe, open_for(Beam::Extraordinary));
            sources.push(SourceTruth {
                name,
                o_xy: [xo, yo],
                e_xy: [xe, ye],
                flux_o: fo,
                flux_e: fe,
            });
        }

        let cr_pixels = self.detector(&mut img, (t as u64, k as u64), s.observation.ndit);

        let file_name = self.file_name(t, k);
        let header = self.header(t, k, &fp, &file_name);
        let frame = Frame::new(img, header).with_history(
            "simulate",
            format!(
                "scene '{}' seed {} target '{}' exposure {}; effects: [{}]",
                s.name,
                s.seed,
                b.name,
                k + 1,
                s.effects.iter().map(|e| e.name()).collect::<Vec<_>>().join(", ")
            ),
        );
        let truth = FrameTruth {
            file: file_name.clone(),
            posang_deg: fp.posang,
            analyzer_deg: fp.phi,
            header_offset_px: fp.header_off,
            true_offset_px: fp.true_off,
            transparency: fp.transparency,
            sky_level_adu: fp.sky_level,
            fwhm_px: fp.psf.fwhm_px(),
            beta: fp.psf.beta(),
            ellipse: match fp.psf {
                psf::Psf::EllipticalMoffat { ratio, pa_deg, .. } => Some([ratio, pa_deg]),
                _ => None,
            },
            sources,
            cosmic_ray_pixels: cr_pixels,
            pointing: fp.pointing,
            telescope: fp.telescope,
        };
        SimFrame {
            file_name,
            frame,
            truth,
        }
    }

    /// What the detector does to the light of any frame (science or calibration), in
    /// order: strips -> flat_field -> nonlinearity -> photon_noise -> read_noise ->
    /// cosmic_rays -> bad_pixels -> saturation (listed effects only). Returns the pixels
    /// hit by cosmic rays.
    pub(super) fn detector(&self, img: &mut Array2<f32>, fkey: (u64, u64), ndit: u32) -> usize {
        let s = &self.scene;
        let g = &self.profile.geometry;
        if s.has(EffectKind::Strips) {
            effects::strips(&self.calls, img, g);
        }
        if let Some(flat) = &self.flat {
            self.calls.hit(EffectKind::FlatField);
            ndarray::Zip::from(&mut *img).and(flat).for_each(|v, &r| *v *= r);
        }
        if s.has(EffectKind::Nonlinearity) {
            let c = s
                .nonlinearity
                .clone()
                .unwrap_or_default()
                .coeff_per_adu
                .unwrap_or(self.profile.detector.nonlin_coeff_per_adu);
            effects::nonlinearity(&self.calls, img, c);
        }
        if s.has(EffectKind::PhotonNoise) {
            effects::photon_noise(
                &self.calls,
                img,
                s.seed,
                fkey,
                self.profile.detector.effective_gain(ndit),
            );
        }
        if s.has(EffectKind::ReadNoise) {
            effects::read_noise(
                &self.calls,
                img,
                s.seed,
                fkey,
                self.profile.detector.read_variance_adu2(ndit).sqrt(),
            );
        }
        let mut cr_pixels = 0;
        if s.has(EffectKind::CosmicRays) {
            cr_pixels = effects::cosmic_rays(
                &self.calls,
                img,
                s.seed,
                fkey,
                &s.cosmic_rays.clone().unwrap_or_default(),
            );
        }
        if let Some(bad) = &self.bad {
            effects::apply_bad_pixels(&self.calls, img, bad);
        }
        if s.has(EffectKind::Saturation) {
            let level = s
                .saturation
                .clone()
                .unwrap_or_default()
                .level_adu
                .unwrap_or(self.profile.detector.saturation_adu);
            effects::saturation(&self.calls, img, level);
        }
        cr_pixels
    }

    fn render(&self, p: psf::Psf, x: f64, y: f64, tail: f64) -> psf::Stamp {
        if !matches!(p, psf::Psf::Point) {
            self.calls.hit(EffectKind::Psf);
        }
        psf::render_with_tail(p, x, y, tail)
    }

    fn header(&self, t: usize, k: usize, fp: &FrameParams, file_name: &str) -> Header {
        let s = &self.scene;
        let o = &s.observation;
        let kw = &self.profile.keywords;
        let b = &self.targets[t];
        let mut h = Header::new(file_name);
        h.set(&kw.instrument, self.profile.matching.instrument.as_str());
        h.set(&kw.object, b.name.as_str());
        h.set(&kw.date_obs, effects::iso_from_mjd(fp.mjd, true));
        h.set(&kw.mjd_obs, fp.mjd);
        h.set(&kw.exptime, o.dit_s);
        h.set(&kw.ra, self.plan[t].ra_deg);
        h.set(&kw.dec, self.plan[t].dec_deg);
        h.set("LST", fp.pointing.start.lst_deg * 240.0);
        if self.is_standard(t) {
            h.set(&kw.dpr_catg, "CALIB");
            h.set(&kw.dpr_type, "STD");
        } else {
            h.set(&kw.dpr_catg, "SCIENCE");
            h.set(&kw.dpr_type, "OBJECT");
        }
        h.set(&kw.dpr_tech, self.profile.matching.polarimetry_tech.as_str());
        h.set(&kw.tpl_id, self.profile.matching.polarimetry_template.as_str());
        h.set(&kw.tpl_start, self.plan[t].tpl_start.as_str());
        h.set(&kw.tpl_nexp, self.frames_per_target() as i64);
        h.set(&kw.tpl_expno, (k + 1) as i64);
        h.set(&kw.targ_name, b.name.replace(' ', "_"));
        h.set(&kw.filter, o.filter.as_str());
        h.set(&format!("{}1 ID", kw.opti_prefix), "MASK_POL");
        h.set(&format!("{}3 ID", kw.opti_prefix), "WOLLASTON");
        h.set(&kw.pixscale, self.scale());
        h.set(&kw.posang, fp.posang);
        h.set(&kw.offset_x, fp.header_off[0]);
        h.set(&kw.offset_y, fp.header_off[1]);
        h.set(&kw.dit, o.dit_s);
        h.set(&kw.ndit, o.ndit as i64);
        let (start, end) = (&fp.pointing.start, &fp.pointing.end);
        h.set(&kw.parang, start.parang_deg);
        h.set(&kw.parang_end, end.parang_deg);
        h.set(&kw.airmass, start.airmass);
        h.set(&kw.airmass_end, end.airmass);
        h.set(&kw.altitude, start.alt_deg);
        h
    }
}
